"""Pose finders: turn place candidates into a 6-DoF ``world_from_cam`` estimate."""

from __future__ import annotations

import abc
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from math import lgamma
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from ...core import features as feature_lib
from ...core.features import FeatureConf
from ...core.frame import Features, Frame
from ...core.map import MapState
from ...core.plugins import Registry, make_conf
from ..place.base import PlaceCandidate
from .intrinsics import IntrinsicsCheck

Array = npt.NDArray[np.float64]

POSE_FINDERS: Registry[PoseFinder] = Registry("pose finder")
register = POSE_FINDERS.register


@dataclass
class PoseEstimate:
    """A pose hypothesis and the evidence for it, to be judged by the verification.

    Geometric evidence (from 2D-3D correspondences) is ``num_matches``, ``inliers``,
    ``reprojection_rms_px`` and ``covariance`` (6x6, twist order (rho, omega), right
    perturbation ``world_from_cam @ exp(xi)``, metres and radians): how well the
    correspondences fix the pose relative to the map (query keypoint noise, landmark depth
    noise), what the verification judges. ``map_covariance`` (same convention) is what the
    errors of the keyframe poses the map was put with add (:mod:`.map_uncertainty`); the
    answer's covariance is the sum of both. Photometric evidence (from image alignment) is
    ``ncc``: zero-mean normalised cross-correlation of aligned thumbnails. Unknown evidence
    stays None.
    """

    world_from_cam: Array
    keyframe_ids: list[int]
    num_matches: int = 0
    inliers: int | None = None
    reprojection_rms_px: float | None = None
    covariance: Array | None = None
    map_covariance: Array | None = None
    ncc: float | None = None
    timings: dict[str, float] = field(default_factory=dict)
    #: (N, 2) query pixels and (N, 3) world points of the inliers, kept for diagnostics/agreement.
    inlier_px: Array | None = None
    inlier_points_world: Array | None = None
    #: (N,) 1-sigma position uncertainty of each inlier's world point, metres (its depth
    #: uncertainty, at least what one pixel of keypoint noise means at its range); None:
    #: unknown. With the points, it tells whether the support is one plane.
    inlier_sigmas_m: Array | None = None
    #: (width, height) of the query image, to judge how the inliers spread over it.
    image_size: tuple[int, int] | None = None
    #: Reprojection error (pixels) under which a correspondence counted as an inlier: with
    #: the image size, the chance that a random correspondence agrees with a wrong pose.
    inlier_threshold_px: float | None = None
    #: Correspondences drawn per hypothesis by the minimal solver (3 for P3P).
    sample_size: int = 3
    #: Probability that a correspondence agrees with the pose by chance, from the data: the
    #: share of (keypoint, point) pairings across the inliers that agree within the
    #: threshold, at least ``pi t^2 / area``. Inliers bunched on one patch (a poster) make
    #: chance agreement likely; spread ones do not. None: the uniform value.
    chance_probability: float | None = None
    #: (matches, inliers) of the consensus found without a pose prior, when the estimate was
    #: then grown by guided matching: the false-alarm test judges these, since matches found
    #: around projections agree with the pose by construction. None: ``num_matches``,
    #: ``inliers``.
    unguided_evidence: tuple[int, int] | None = None
    #: (N,) indices of the inliers' query keypoints (in the finder's features) and (N,) the
    #: ids of their landmarks, where the finder knows them: what a repetition of the map
    #: around the pose is looked for with (:mod:`.repetition`).
    inlier_keypoints: npt.NDArray[np.int64] | None = None
    inlier_landmark_ids: npt.NDArray[np.int64] | None = None
    #: The test of the query's intrinsics on the pose's correspondences
    #: (:mod:`.intrinsics`, judged by :func:`.map_consistency.settle_intrinsics`); None
    #: where not tested (too few inliers, or no correspondences). Where it passes,
    #: ``covariance`` includes what the intrinsics the data cannot exclude do to the pose.
    intrinsics: IntrinsicsCheck | None = None
    #: Where the intrinsics test passed: the covariance with the given intrinsics trusted
    #: within their calibration prior alone (``covariance`` also marginalises what the data
    #: cannot exclude); the one answered where the view cannot bound them
    #: (:func:`~reloc_service.algorithms.relocalizers.base.stated_covariance`).
    covariance_given_intrinsics: Array | None = None
    #: How the solver tests the intrinsics on its correspondences, run when the estimate is
    #: judged (the few estimates verification sees, not every RANSAC solve); None where the
    #: solver cannot.
    intrinsics_test: Callable[[], IntrinsicsCheck | None] | None = field(default=None,
                                                                          repr=False)
    #: (2, 2) how well the map states its camera calibration is known (the map's
    #: :attr:`~reloc_service.core.map.MapState.calibration_covariance`, set where the
    #: estimate is settled against the map): what the answer's covariance trusts the
    #: calibration within (:mod:`.intrinsics_marginal`); None: the intrinsics test's prior.
    #: Read by the stated covariance only, never by a decision.
    calibration_covariance: Array | None = None
    #: The map's dispersion around the pose robust to mis-associated landmarks
    #: (:func:`.map_consistency.map_dispersion` with ``robust``), which the stated covariance
    #: scales the pose's own part by in place of the decision's (``intrinsics.dispersion``);
    #: None: the decision's. Read by the stated covariance only, never by a decision.
    stated_dispersion: float | None = None
    #: Whether the stated covariance of a pose grown by guided matching, where the query
    #: does not claim the map's calibration, covers what its unguided matches cannot exclude
    #: about the intrinsics (:func:`.intrinsics_envelope.unguided_widening`; the option
    #: ``stated_unguided_intrinsics``). Read by the stated covariance only, never by a decision.
    stated_unguided_intrinsics: bool = False
    #: The cluster-robust covariance of the pose over the coverage grid's cells and their
    #: number (:func:`.cell_sandwich.cell_sandwich`), computed when the answer's covariance
    #: is stated, which widens its measurement part where it exceeds it
    #: (:func:`.cell_sandwich.widened`); None where the solver gives none. Read by the stated
    #: covariance only, never by a decision.
    measurement_sandwich: Callable[[], tuple[Array, int] | None] | None = field(
        default=None, repr=False, compare=False)
    #: The same with each inlier its own cluster (White's heteroskedasticity-robust
    #: covariance) and the number of inliers, which widens the answer's covariance relative
    #: to the map where it exceeds it (:func:`.cell_sandwich.widened`); None where the solver
    #: gives none or ``stated_point_sandwich`` is off. Read by the stated covariance only.
    point_sandwich: Callable[[], tuple[Array, int] | None] | None = field(
        default=None, repr=False, compare=False)
    #: (6, 6) what the measurement part of the covariance lacks where the inlier gate cut
    #: the keypoint noise's tails (:mod:`.gate_truncation`), added to the answer's
    #: covariance; None where the solver gives none or ``stated_gate_truncation`` is off.
    #: Read by the stated covariance only.
    gate_truncation: Callable[[], Array | None] | None = field(
        default=None, repr=False, compare=False)
    #: Whether the query claims exactly the camera of the keyframes behind the pose (the
    #: map's calibration, as a drone whose camera built the map), which is what a view
    #: that cannot check the intrinsics may trust; None where not known (not trusted).
    query_camera_is_map_calibration: bool | None = None
    #: The settling a pose finder left for verification to run (the intrinsics test and the
    #: map's errors, :meth:`PoseFinder.find_pose_deferred`): verification runs it only once
    #: the cheaper tests that do not read its outcome have passed. None: settled, or nothing
    #: to settle.
    deferred_settling: Callable[[], None] | None = field(default=None, repr=False,
                                                         compare=False)

    def settle(self) -> None:
        """Run :attr:`deferred_settling`, once (nothing when there is none)."""
        pending, self.deferred_settling = self.deferred_settling, None
        if pending is not None:
            pending()


@dataclass(frozen=True, eq=False)
class Support:
    """The query keypoints a pose explains: (E,) ``keypoints`` (ascending query keypoint
    indices) matched to (E,) ``landmark_ids`` of the local map where the pose projects them,
    out of ``predicted`` local-map landmarks the pose puts inside the image."""

    keypoints: npt.NDArray[np.int64]
    landmark_ids: npt.NDArray[np.int64]
    predicted: int

    def __len__(self) -> int:
        return len(self.keypoints)

    @classmethod
    def empty(cls) -> Support:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), 0)


def total_covariance(estimate: PoseEstimate, own: Array | None = None) -> Array | None:
    """The covariance of ``estimate`` relative to the world: its own (``own`` where given,
    else its ``covariance``; relative to the map) plus its ``map_covariance`` (the keyframe
    poses' errors, independent of the measurements); None without an own covariance."""
    own = estimate.covariance if own is None else own
    if own is None:
        return None
    if estimate.map_covariance is None:
        return own
    return np.asarray(own + estimate.map_covariance, np.float64)


def log10_false_alarms(num_matches: int, inliers: int, sample_size: int, p: float) -> float:
    """log10 of the number of false alarms of a consensus (ORSA, Moisan & Stival 2004): the
    expected number of subsets of ``inliers`` among ``num_matches`` correspondences that a
    wrong model, fitted to ``sample_size`` of them, would explain by chance when each agrees
    with probability ``p``: ``NFA = (n - s) C(n, k) C(k, s) p^(k - s)``; inf when
    ``k <= s``."""
    n, k, s = int(num_matches), int(inliers), int(sample_size)
    if k <= s or n < k:
        return float("inf")
    # log C(n, k) + log C(k, s) = log n! - log (n - k)! - log s! - log (k - s)!
    log_c = lgamma(n + 1) - lgamma(n - k + 1) - lgamma(s + 1) - lgamma(k - s + 1)
    return float(np.log10(max(n - s, 1)) + log_c / np.log(10) + (k - s) * np.log10(p))


class PoseFinder(abc.ABC):
    """Finds the query's pose from the place finder's candidates (thesis 4, figure 4.3)."""

    name: ClassVar[str]
    #: Feature kinds keyframes must carry (an instance may set its own from its conf).
    required_features: frozenset[str] = frozenset()
    #: Whether it matches a query against map keyframes' keypoints that carry no landmark
    #: (2D-2D matching): a map served with it keeps every keypoint on disk.
    reads_unmapped_keypoints: ClassVar[bool] = False
    #: Whether it reads keyframe pixels (beyond features and small blurry images): a map
    #: served with it keeps its keyframe images on disk.
    reads_keyframe_images: ClassVar[bool] = False

    #: True if the finder uses all candidates jointly (landmarks pooled), False if one at a time.
    pools_candidates: ClassVar[bool] = False
    #: True for photometric finders (none, esm): aligned images prove similar views, not the
    #: camera's position, so two candidate keyframes must independently agree on the pose.
    needs_agreement: ClassVar[bool] = False

    @dataclass(frozen=True)
    class Conf:
        pass

    def __init__(self, conf: Any) -> None:
        self.conf = conf

    @abc.abstractmethod
    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        """Best estimate from ``candidates`` (best first) in map ``state``; None if none."""

    def find_pose_deferred(self, query: Frame, candidates: list[PlaceCandidate],
                           state: MapState, *, known: Callable[[PoseEstimate], bool] | None = None
                           ) -> PoseEstimate | None:
        """:meth:`find_pose`, with whatever settling of the estimate only verification reads
        left in :attr:`PoseEstimate.deferred_settling` (for a caller that verifies every
        estimate at once: most fail a cheaper test first). ``known``, where given, tells a
        pose of a solution the caller has verified already: a finder may return a pose
        ``known`` recognises as soon as it has one, before refining it further (the caller
        sets it aside unverified). Default: :meth:`find_pose`."""
        return self.find_pose(query, candidates, state)

    def support(self, query: Frame, world_from_cam: Array, state: MapState) -> Support | None:
        """The query keypoints the map around ``world_from_cam`` explains
        (:mod:`.support`), for comparing hypotheses; None when this finder has no
        features to judge by (photometric finders). Call after :meth:`find_pose` on
        ``query``: it reads the features that extracted."""
        return None

    def alternatives(self, query: Frame, estimate: PoseEstimate, state: MapState, *,
                     plausible: Callable[[PoseEstimate], bool] = lambda _: True
                     ) -> list[PoseEstimate]:
        """Other poses the map around ``estimate`` offers for the same query keypoints
        (:mod:`.repetition`: twins of its landmarks nearby), unverified; ``plausible``
        says which first consensus is worth growing. Default: none."""
        return []

    def prepare_map(self, state: MapState) -> None:  # noqa: B027 (optional hook)
        """Work on the whole map done ahead of queries (when the relocalizer trains);
        default: none."""

    def prepare_candidates(self, query: Frame, candidates: list[PlaceCandidate],
                           state: MapState) -> dict[str, float]:
        """The work of :meth:`find_pose` on ``candidates`` that needs the map alone, not the
        query's features, done ahead and cached in ``query.cache`` (the multi relocalizer
        runs it on its helper thread, beside :meth:`prepare_query`); the seconds of each
        stage. Default: nothing."""
        return {}

    def feature_confs(self) -> dict[str, FeatureConf]:
        """The query features :meth:`find_pose` extracts, by kind, with the settings it
        extracts them with (so they can be extracted ahead, elsewhere, to the same
        result); default: none."""
        return {}

    def query_features(self, query: Frame, timings: dict[str, float]) -> Features:
        """The query's features of the one kind :meth:`feature_confs` names, extracted once
        and cached on the frame (or waited for, when extracted ahead:
        :meth:`Frame.features_of`), so pose finders of one kind share them;
        ``timings["features"]`` is the time this took."""
        start = time.perf_counter()
        (kind, conf), = self.feature_confs().items()
        feats = query.features_of(kind, lambda: feature_lib.extract(query.image, conf))
        timings["features"] = time.perf_counter() - start
        return feats

    def query_kinds(self, query: Frame) -> frozenset[str]:
        """Feature kinds :meth:`prepare_query` would extract for ``query`` (none yet cached
        on it); empty when it has nothing to do."""
        return frozenset()

    def prepare_query(self, query: Frame) -> dict[str, float]:
        """The work of :meth:`find_pose` that needs the query image alone (its features),
        done ahead and cached on ``query``; the seconds of each stage. The multi
        relocalizer runs it while the place finder ranks keyframes on a helper thread, so
        it writes only ``query.features[kind]`` for :meth:`query_kinds`."""
        return {}


def create_pose_finder(options: dict[str, Any]) -> PoseFinder:
    """``create_pose_finder({"name": "p3p", **options})``."""
    opts = dict(options)
    name = opts.pop("name", None)
    cls = POSE_FINDERS.lookup(str(name))
    return cls(make_conf(cls.Conf, opts, owner=f"pose finder {name}"))
