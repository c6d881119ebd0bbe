"""How well a map agrees with its own camera: each keyframe tested like a query
(:func:`.intrinsics.check_intrinsics`) on its landmarks re-triangulated without it, and how
much more those tests' intrinsics estimates vary than their covariances say.

A map built from imprecise keyframe poses (a motion-capture or KinectFusion ground truth a
few centimetres off) bends its landmarks slightly differently in each region: seen from a
query, that bend looks like a focal or distortion error the query's own correspondences
cannot tell from a real one. The keyframes measure it: held out of its landmarks (each
re-triangulated from its other observations, as a query's landmarks never saw the query), a
keyframe whose camera is the map's by definition estimates ``theta`` as a query would, and
the spread of those estimates beyond their model covariance is the map's. The statistic is
the quasi-likelihood dispersion (McCullagh & Nelder 1989, 9.2): the median over keyframes of
``T^2 = theta^T V^-1 theta`` over the median of chi-square with 2 degrees of freedom (the
median, so that a keyframe with a gross error does not set it), at least 1.

On repeated texture some held-out landmarks are mis-associated: their residual in the held-out
keyframe is that of a wrong correspondence (a few pixels, inside the consensus threshold),
not extra noise of the map, and ``T^2`` grows with them although a query's own consensus
keeps such outliers out of its pose. The dispersion an answer may state (``robust=True``,
:attr:`.base.PoseEstimate.stated_dispersion`, where ``[options.p3p]
robust_stated_dispersion`` asks for it, as by default) therefore estimates each
keyframe's ``T^2`` on its inliers of a chi-square gate: the held-out residuals' squared
lengths in units of their keypoint sigmas, over their robust scale (median over the median
of chi-square with 2 degrees of freedom, so the outliers do not set it), beyond the
``1 - HELD_OUT_FALSE_ALARM`` quantile are outliers and left out. The gate truncates the noise
and the a-posteriori variance of the test alike, so ``T^2`` needs no truncation correction
(both shrink by the same factor, about 5 % at a 1 % false-alarm rate). A keyframe's gated
statistic replaces its plain one only where the gate left out more residuals than honest
ones explain (:func:`excess_exclusion`: a binomial test of the count left out against the
gate's nominal rate, at a ``MIS_ASSOCIATION_FALSE_ALARM`` rate): elsewhere the tail beyond
the gate is the map's own noise, which a query's pose sees as well, and the plain statistic
stands. The verification's decisions keep the plain dispersion: only the stated covariance
reads the robust one. A weakness: the keyframes of degraded images (blur, noise) fail the
test as well, with a few per cent of their held-out residuals beyond the gate's 99.9 %
quantile, and there the plain dispersion was what covered the queries' own correlated errors,
which the model covariance does not (room-hard's cov scale 1.27 -> 1.45 with the robust
dispersion alone); the answer's measurement part is widened to its inliers' spread over the
image's cells for them (:mod:`.cell_sandwich`), without which the robust dispersion would
make degraded sets too confident.

A keyframe's statistics are computed once and kept with its features; a save stores them
beside the models, each with the digest of what it was computed from, and a load gives them
back to the keyframes (:func:`held_statistics`, :func:`offer_statistics`,
:mod:`.consistency_store`), so that the first queries of a loaded map compute only those of
keyframes whose inputs changed.
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from ...core import distributions as stats
from ...core.frame import Features, Keyframe
from ...core.geometry import invert, transform_points
from ...core.landmark_table import LandmarkColumns
from ...core.map import MapState
from ...core.triangulation import ViewObservations, keypoint_sigmas
from .base import PoseEstimate
from .cell_correlation import CellComponents, CellCorrelation, pooled_correlation
from .consistency_store import InputsDigest, KeyframeStatistics
from .guided import GuidedConf
from .held_out import HeldOutViews, held_out_candidates, held_out_views, points_held_out
from .intrinsics import IntrinsicsCheck, cell_shared_components, check_intrinsics
from .intrinsics_power import blind_spot_factor, governing_covariance
from .map_uncertainty import map_covariance
from .pnp_conf import PnPConf
from .projection import pose_projector

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Median of chi-square with 2 degrees of freedom: ``2 ln 2``.
CHI2_2_MEDIAN = float(stats.chi2.median(2))

#: Held-out landmarks a keyframe needs for its statistic (the test's own floor is 8 inliers;
#: the dispersion needs estimates as good as a query's; the most it uses is
#: :data:`.held_out.MAX_HELD_OUT`).
MIN_HELD_OUT = 30

#: The share of honest held-out residuals the robust statistic's gate leaves out (its
#: false-alarm rate).
HELD_OUT_FALSE_ALARM = 0.01

#: The rate at which a keyframe whose held-out residuals are honest is taken for one with
#: mis-associated landmarks (:func:`excess_exclusion`): the binomial test's false-alarm rate.
MIS_ASSOCIATION_FALSE_ALARM = 0.01

#: Per keyframe features, the plain and the gated (robust) statistics of that keyframe
#: (None: too few held-out landmarks):
#: features are replaced, not changed in place, when their landmarks change, so an entry lives
#: as long as the landmarks it was computed on (other keyframes' later observations of them
#: refine it a little; the median over keyframes does not hang on one).
_STATISTICS: weakref.WeakKeyDictionary[Features, dict[bool, float | None]] = (
    weakref.WeakKeyDictionary())

#: Per keyframe features, the variance components over the image cells of the held-out
#: residuals (:mod:`.cell_correlation`; None: too few held-out landmarks), computed with the
#: statistics from the same held-out points where ``unguided_cell_correlation`` asks.
_CELLS: weakref.WeakKeyDictionary[Features, CellComponents | None] = weakref.WeakKeyDictionary()

#: Per keyframe and feature kind, what the last computation of its statistics gave with the
#: digest of what it read, or what a snapshot stored for it (:func:`offer_statistics`):
#: what a save stores (:func:`held_statistics`), and what a computation whose inputs have
#: that digest gives without computing. Keyed by the keyframe, not its features, so that
#: neither a save nor a load builds a keyframe's features (a keyframe whose features change
#: is a new object).
_RECORDS: weakref.WeakKeyDictionary[Keyframe, dict[str, KeyframeStatistics]] = (
    weakref.WeakKeyDictionary())

#: The name of this computation in the digests of its inputs: changed with anything that
#: makes it compute other values from the same inputs, so that statistics stored by another
#: computation are not taken for its own.
STATISTIC_VERSION = "held-out intrinsics T^2, 1"


def map_dispersion(state: MapState, kind: str, keyframe_ids: list[int], conf: PnPConf, *,
                   robust: bool = False) -> float:
    """The dispersion of ``kind`` intrinsics estimates over ``keyframe_ids`` (module
    docstring): at least 1, and 1 where fewer than 3 keyframes give a statistic. ``robust``:
    each keyframe's statistic on its held-out residuals' chi-square inliers (what an answer
    states), else on all within the consensus threshold (what decisions weigh)."""
    columns = _Columns(state)
    values = [t2 for k in keyframe_ids if k in state.keyframes
              and (t2 := keyframe_statistic(state, k, kind, conf, columns, robust=robust))
              is not None]
    if len(values) < 3:
        return 1.0
    return max(1.0, float(np.median(values)) / CHI2_2_MEDIAN)


def map_cell_correlation(state: MapState, kind: str, keyframe_ids: list[int], conf: PnPConf
                         ) -> CellCorrelation | None:
    """The intra-cell correlation of ``kind`` reprojection errors the held-out residuals of
    ``keyframe_ids`` show (:func:`.cell_correlation.pooled_correlation`); None where fewer
    than its minimum of keyframes have enough held-out landmarks."""
    columns = _Columns(state)
    components = []
    for k in keyframe_ids:
        if k not in state.keyframes or (feats := state.keyframes[k].features.get(kind)) is None:
            continue
        if feats not in _CELLS:  # its statistics were computed without the cells' entry
            _STATISTICS.pop(feats, None)  # (same values again, with it)
        keyframe_statistic(state, k, kind, conf, columns)  # fills the cells' entry (cached)
        if (found := _CELLS.get(feats)) is not None:
            components.append(found)
    return pooled_correlation(components)


class _Columns:
    """The landmark columns of a map state, merged once when first needed (a state whose
    landmarks changed since its last compaction merges them on every request)."""

    def __init__(self, state: MapState) -> None:
        self._state = state
        self._columns: LandmarkColumns | None = None

    def get(self) -> LandmarkColumns:
        if self._columns is None:
            self._columns = self._state.landmarks.columns()
        return self._columns


def keyframe_statistic(state: MapState, kf_id: int, kind: str, conf: PnPConf,
                       columns: _Columns | None = None, *, robust: bool = False) -> float | None:
    """``T^2`` of keyframe ``kf_id``'s intrinsics estimate on its ``kind`` landmarks
    re-triangulated without it (cached with its features; given by a snapshot's record of
    the same inputs where the map was loaded: :func:`offer_statistics`); None where fewer than
    :data:`MIN_HELD_OUT` of them are observed by two other keyframes. ``robust``: on the
    residuals within the gate of :func:`gated_inliers` where it left out more than honest
    ones explain (:func:`excess_exclusion`; None where fewer than :data:`MIN_HELD_OUT` pass
    it), else the plain statistic."""
    feats = state.keyframes[kf_id].features.get(kind)
    if feats is None:
        return None
    cached = _STATISTICS.setdefault(feats, {})
    if robust not in cached:
        # Where answers state the gated statistic, both share one set of held-out points.
        both = conf.robust_stated_dispersion and not cached
        cached.update(_statistics(state, kf_id, kind, conf, columns or _Columns(state),
                                  (False, True) if both else (robust,)))
    return cached[robust]


def _statistics(state: MapState, kf_id: int, kind: str, conf: PnPConf, columns: _Columns,
                wanted: tuple[bool, ...]) -> dict[bool, float | None]:
    """The plain (False) and the gated (True) ``T^2`` of keyframe ``kf_id``
    (:func:`keyframe_statistic`) for each of ``wanted`` (and any other its record holds),
    from one set of held-out points: recorded with the digest of what they were computed
    from, or given by a record of the same digest (a snapshot's) without computing."""
    keyframe = state.keyframes[kf_id]
    feats = keyframe.features[kind]
    if conf.unguided_cell_correlation:
        _CELLS[feats] = None
    cols = columns.get()
    if kind not in cols.kinds:
        return dict.fromkeys(wanted)
    observed, rows = held_out_candidates(cols, feats.landmark_ids)
    views = held_out_views(state, cols, rows, kf_id, kind)
    digest = _inputs_digest(keyframe, feats, observed, cols.ids[rows], views, conf)
    record = _RECORDS.get(keyframe, {}).get(kind)
    if record is None or not _answers(record, digest, wanted, conf):
        record = _computed(keyframe, feats, observed, views, conf, wanted, digest)
        _record(keyframe, kind, record)
    if conf.unguided_cell_correlation:
        _CELLS[feats] = record.cells
    return dict(record.values)


def _answers(record: KeyframeStatistics, digest: bytes, wanted: tuple[bool, ...],
             conf: PnPConf) -> bool:
    """Whether ``record`` holds every statistic of ``wanted`` (and the cells' entry, where
    ``conf`` asks for it) as computed from inputs of ``digest``."""
    return (record.digest == digest and all(robust in record.values for robust in wanted)
            and (record.has_cells or not conf.unguided_cell_correlation))


def _record(keyframe: Keyframe, kind: str, record: KeyframeStatistics) -> None:
    """Keep ``record`` as ``keyframe``'s ``kind`` statistics, with what its earlier record
    holds from the same inputs."""
    held = _RECORDS.setdefault(keyframe, {})
    earlier = held.get(kind)
    held[kind] = record if earlier is None else earlier.merged(record)


def _inputs_digest(keyframe: Keyframe, feats: Features, observed: IntArray,
                   landmark_ids: IntArray, views: HeldOutViews, conf: PnPConf) -> bytes:
    """The digest of what :func:`_computed` reads: the options it tests with, the keyframe
    (camera, pose, the keypoints of its held-out landmarks ``landmark_ids``: pixels and
    noise) and the other keyframes' observations those landmarks are re-triangulated from
    (:class:`HeldOutViews`). Keypoint indices are not part of it, only what they point
    at: a snapshot that keeps only landmark keypoints numbers them afresh."""
    digest = InputsDigest(STATISTIC_VERSION)
    digest.text(feats.kind)
    digest.array(np.array([conf.max_reproj_error_px, conf.min_sigma_px,
                           *dataclasses.astuple(conf.intrinsics_prior)], np.float64))
    digest.array(np.asarray(landmark_ids, np.int64))
    digest.view(ViewObservations(keyframe.camera, invert(keyframe.world_from_cam),
                                 np.arange(len(observed)),
                                 feats.keypoints_px[observed].astype(np.float64),
                                 keypoint_sigmas(feats)[observed]))
    for view in (*views.others, *views.own):
        digest.view(view)
    digest.array(views.exact)
    # The measured points in the form a snapshot stores them, so that a map lifted from
    # depth maps, saved and loaded, still finds its statistics.
    digest.array(views.stored_offsets())
    return digest.digest()


def _computed(keyframe: Keyframe, feats: Features, observed: IntArray, views: HeldOutViews,
              conf: PnPConf, wanted: tuple[bool, ...], digest: bytes) -> KeyframeStatistics:
    """The statistics of ``wanted`` of ``keyframe`` on the landmarks of its keypoints
    ``observed`` held out as ``views`` says, and its cells' variance components where
    ``conf`` asks for them (:func:`keyframe_statistic`), recorded under ``digest``."""
    points, held = points_held_out(views)
    if held.sum() < MIN_HELD_OUT:
        return KeyframeStatistics(digest, dict.fromkeys(wanted), conf.unguided_cell_correlation)
    px = feats.keypoints_px[observed[held]].astype(np.float64)
    points = points[held]
    project = pose_projector(points, keyframe.camera)
    projected, _ = project(keyframe.world_from_cam)
    with np.errstate(invalid="ignore"):
        inliers = np.flatnonzero(np.linalg.norm(px - projected, axis=1) < conf.max_reproj_error_px)
    weights = 1.0 / keypoint_sigmas(feats)[observed[held]] ** 2
    gated = gated_inliers(np.sum((px - projected) ** 2, axis=1) * weights, inliers)
    cells = None
    if conf.unguided_cell_correlation and len(inliers) >= MIN_HELD_OUT:
        cells = cell_shared_components(keyframe.world_from_cam, px, inliers, weights,
                                       keyframe.camera, project,
                                       threshold_px=conf.max_reproj_error_px)

    def statistic(use: IntArray, subset: bool) -> float | None:
        # ``subset``: only the correspondences ``use`` are given to the test, which re-gates
        # at the consensus threshold as it refines and would take gated ones back.
        rows = np.arange(len(use)) if subset else use
        given = use if subset else np.arange(len(px))
        depths = transform_points(invert(keyframe.world_from_cam), points[use])[:, 2]
        check = check_intrinsics(keyframe.world_from_cam, px[given], rows, weights[given],
                                 keyframe.camera,
                                 pose_projector(points[given], keyframe.camera) if subset
                                 else project,
                                 depth_m=float(np.median(depths)) if len(depths) else 1.0,
                                 focal_starts=(),  # a keyframe's camera is the map's: no search
                                 threshold_px=conf.max_reproj_error_px,
                                 min_sigma_px=conf.min_sigma_px, prior=conf.intrinsics_prior)
        if check is None or check.inliers < MIN_HELD_OUT:
            return None
        return check.data_statistic

    # The gated statistic is the plain one where the gate left out no more than honest
    # residuals explain: computed once for both.
    plain_stands = not excess_exclusion(len(inliers) - len(gated), len(inliers))
    values: dict[bool, float | None] = {}
    if False in wanted or plain_stands:
        values[False] = statistic(inliers, subset=False)
    if True in wanted:
        values[True] = (values[False] if plain_stands
                        else None if len(gated) < MIN_HELD_OUT
                        else statistic(gated, subset=True))
    return KeyframeStatistics(digest, {robust: values[robust] for robust in wanted},
                              conf.unguided_cell_correlation, cells)


def excess_exclusion(excluded: int, total: int, *,
                   gate_false_alarm: float = HELD_OUT_FALSE_ALARM,
                   false_alarm: float = MIS_ASSOCIATION_FALSE_ALARM) -> bool:
    """Whether a chi-square gate that left out ``excluded`` of ``total`` residuals left out
    more than honest ones explain: the one-sided binomial test of ``excluded`` against the
    gate's nominal rate ``gate_false_alarm``, ``P(X >= excluded) < false_alarm`` for ``X ~
    Binomial(total, gate_false_alarm)``."""
    if excluded <= 0 or total <= 0:
        return False
    return stats.binom.sf(excluded - 1, total, gate_false_alarm) < false_alarm


def gated_inliers(squared: Array, inliers: IntArray,
                  false_alarm: float = HELD_OUT_FALSE_ALARM) -> IntArray:
    """The ``inliers`` whose weighted squared residuals ``squared`` (N,) (chi-square with 2
    degrees of freedom times an unknown scale, for honest ones) lie within the
    ``1 - false_alarm`` quantile of that distribution, the scale estimated robustly from the
    inliers' median (the median of chi-square 2 its consistency factor)."""
    values = squared[inliers]
    if len(values) == 0:
        return inliers
    scale = float(np.median(values)) / CHI2_2_MEDIAN
    return inliers[values <= scale * float(stats.chi2.isf(false_alarm, 2))]


def settle_intrinsics(estimate: PoseEstimate, state: MapState, kind: str, conf: PnPConf) -> None:
    """Run ``estimate``'s intrinsics test (once) and judge it with the dispersion of the map
    around the pose (the keyframes guided matching would project there: the landmarks the
    query sees); where it passes, the estimate's covariance becomes
    :func:`covariance_with_intrinsics`'s."""
    if estimate.intrinsics is not None or estimate.intrinsics_test is None:
        return  # judged already, or nothing to judge
    check = estimate.intrinsics_test()
    if check is None or estimate.covariance is None:
        return
    guided = GuidedConf()
    near = state.nearest_keyframes(estimate.world_from_cam, guided.local_keyframes,
                                   guided.max_view_angle_deg)
    check = check.with_dispersion(map_dispersion(state, kind, near, conf))
    if conf.unguided_cell_correlation and check.unguided is not None:
        correlation = map_cell_correlation(state, kind, near, conf)
        if correlation is not None:
            check = check.with_unguided_cell_correlation(correlation.upper)
    if conf.robust_stated_dispersion:
        estimate.stated_dispersion = map_dispersion(state, kind, near, conf, robust=True)
    estimate.stated_unguided_intrinsics = conf.stated_unguided_intrinsics
    estimate.intrinsics = check
    if check.passed:
        estimate.covariance_given_intrinsics = covariance_with_intrinsics(
            estimate.covariance, check, trusted=True)
        estimate.covariance = covariance_with_intrinsics(estimate.covariance, check)


def settle_pose_errors(estimate: PoseEstimate, state: MapState, kind: str, conf: PnPConf,
                       landmark_ids: npt.ArrayLike | None) -> PoseEstimate:
    """``estimate`` with both the errors it owes to others: the intrinsics' (judged,
    :func:`settle_intrinsics`; the map's stated calibration accuracy noted for the answer's
    covariance) and the keyframe poses' behind its inliers' ``landmark_ids``
    (:func:`.map_uncertainty.map_covariance`), the latter only where it has a covariance to
    add them to."""
    settle_intrinsics(estimate, state, kind, conf)
    estimate.calibration_covariance = state.calibration_covariance
    if landmark_ids is not None and estimate.covariance is not None:
        estimate.map_covariance = map_covariance(estimate.world_from_cam, state, landmark_ids)
    return estimate


def covariance_with_intrinsics(covariance: Array, check: IntrinsicsCheck, *,
                               trusted: bool = False) -> Array:
    """(6, 6) the expected squared error of the pose estimated at the given intrinsics, whose
    ``covariance`` assumed them exact: the pose is off by ``B theta`` for the intrinsics'
    error ``theta``, which the data put at ``N(theta_hat, V)`` (``V`` the model covariance
    times the map's dispersion) and a correct calibration within the prior ``P``, so
    ``d C + B (theta_hat theta_hat^T + V + P) B^T``, with ``d`` the dispersion (the map's
    errors reach the pose as they reach ``theta``). ``B V B^T`` makes the focal and the
    distortion free unknowns (the joint normal equations' pose block, by the Schur
    complement), marginalised over what the data cannot exclude; ``B theta_hat`` is the shift
    they say the pose has, where the test is too weak to refuse it (keypoints as coarse as
    ORB's let a 5 % focal error pass). Beyond what the local covariance sees, the farthest
    solution the data cannot exclude (:attr:`IntrinsicsCheck.unexcluded_twist`: a scene
    with little depth fits a wrong focal from a pose far away about as well) adds its shift
    ``s s^T``. A pose answered is one whose test passed, and under a stale calibration those
    are the queries whose ``theta_hat`` noise pulled towards zero: ``V + P`` is widened by
    ``(k - 1) W`` (:func:`.intrinsics_power.blind_spot_factor` ``k``, ``W`` the governing
    test covariance) so that every error the test misses more often than its missed-detection
    rate moves the pose within 3 sigma. ``trusted``: the given intrinsics trusted within the
    prior, ``d C + B P B^T``."""
    shift, theta = check.pose_shift, check.theta
    intrinsics = check.prior.covariance
    if not trusted:
        widening = blind_spot_factor(check) - 1.0
        intrinsics = intrinsics + check.covariance + widening * governing_covariance(check)
    stated = check.dispersion * covariance + shift @ intrinsics @ shift.T
    if trusted:
        return stated
    far = check.unexcluded_twist
    return stated + shift @ np.outer(theta, theta) @ shift.T + np.outer(far, far)


def prepare_map(state: MapState, kind: str, conf: PnPConf) -> None:
    """Compute every keyframe's statistic ahead of the queries that would otherwise pay for
    it (a tenth of a second per keyframe; cached with the keyframe's features): the plain
    one the decisions read and, where answers state it (``conf.robust_stated_dispersion``),
    the gated one, which :func:`settle_intrinsics` reads for every keyframe near a pose
    that reaches the test. The values are those a query would compute on the same state."""
    columns = _Columns(state)
    for kf_id in state.keyframe_ids():
        keyframe_statistic(state, kf_id, kind, conf, columns)


def held_statistics(state: MapState, kind: str) -> dict[int, KeyframeStatistics]:
    """Per keyframe of ``state`` (id), its ``kind`` statistics as last computed with the
    digest of their inputs, or as a snapshot stored them (:func:`offer_statistics`) where
    none was computed here: what a save stores beside the models. No keyframe's features
    are built."""
    return {kf_id: record for kf_id, keyframe in state.keyframes.items()
            if (record := _RECORDS.get(keyframe, {}).get(kind)) is not None}


#: Bytes one keyframe's record of one feature kind holds in memory (the record, its digest,
#: values and cells, and its share of the keyframe's entry in the records' table): a bound
#: on what they take by tracemalloc (500-610 bytes), for the memory budget's count.
RECORD_BYTES = 640


def statistics_bytes(state: MapState) -> int:
    """Bytes the statistics records of ``state``'s keyframes hold (:data:`RECORD_BYTES`
    each): about 1.3 MB for 1000 keyframes of two feature kinds, counted with the map's
    pools against a service's memory budget."""
    records = _RECORDS
    return RECORD_BYTES * sum(len(records.get(keyframe, ()))
                              for keyframe in state.keyframes.values())


def offer_statistics(state: MapState, kind: str, stored: Mapping[int, KeyframeStatistics]
                     ) -> int:
    """Give the keyframes of ``state`` the ``kind`` statistics a snapshot ``stored`` for
    them (keyframe id -> entry; ids not in ``state`` ignored): the first computation of a
    keyframe's statistic whose inputs have the entry's digest gives its values instead of
    computing them (:func:`keyframe_statistic`); another computes. A keyframe that has a
    record of its own keeps it. Returns the number of entries given."""
    given = 0
    for kf_id, entry in stored.items():
        keyframe = state.keyframes.get(kf_id)
        if keyframe is not None and kind not in _RECORDS.get(keyframe, {}):
            _RECORDS.setdefault(keyframe, {})[kind] = entry
            given += 1
    return given
