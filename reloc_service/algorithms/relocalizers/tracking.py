"""Localization with a prior (``"track"``): a query that comes with a pose prior and its
covariance (a VIO's pose composed with ``map_from_odom``) is a tracking problem. The
landmarks of the keyframes that see what the prior sees are projected with the prior, each
is matched only to the query keypoints inside the chi-square gate of its projection's
covariance (:mod:`..pose.prior_windows`), then PnP LO-RANSAC with refinement and the
shared verification (:func:`.base.result_from_estimate`), unchanged but for the chance
model: a wrong match was drawn from its window, not from the whole image.

:func:`relocalize_with_prior` runs it before any method when the prior carries a
covariance and falls back to that method when tracking does not verify."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core import distributions as stats
from ...core import features as feature_lib
from ...core.errors import ConfigError
from ...core.frame import Features, Frame, Keyframe
from ...core.geometry import invert, se3_log, transform_points
from ...core.map import KeyframeMap, MapState
from ...core.methods import MethodStep
from ...core.plugins import make_conf
from ..pose.base import PoseEstimate
from ..pose.cluster_covariance import at_least, cluster_robust_covariance
from ..pose.guided import GuidedConf, background_distance
from ..pose.intrinsics import IntrinsicsCheck
from ..pose.landmark_keyframe_errors import keyframe_pose_sigmas, widen_for_keyframe_errors
from ..pose.landmark_matches import union_matches
from ..pose.landmark_pool import LandmarkPool
from ..pose.map_consistency import settle_pose_errors
from ..pose.pnp import solve_pnp_indexed
from ..pose.pnp_conf import PnPConf
from ..pose.point_uncertainty import PointUncertainty
from ..pose.prior_focal import axis_variance, focal_reach, focal_starts_within
from ..pose.prior_gain import narrower_everywhere, narrows_prior
from ..pose.prior_windows import (
    match_in_windows,
    pixel_sigmas,
    predict_windows,
    search_around,
)
from ..pose.regated_refinement import refine_from
from .base import Prior, Relocalizer, RelocResult, VerifyConf, register, result_from_estimate
from .chain_hooks import narrow_support
from .multi import STEP_FEATURES

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: The method name a tracked answer carries (``RelocResult.method``).
TRACK = "track"
#: Local maps (landmark pool and uncertainty of one keyframe set) a tracker keeps: a few
#: cameras tracked at once, each seeing one set for many frames.
LOCAL_MAPS_KEPT = 8
#: The ways a tracked pose grows onto the matches found around it (``Conf.growth``).
GROWTH = ("ransac", "regated")
#: How a tracked pose must narrow its prior (``Conf.narrowing``).
NARROWING = ("every direction", "image average")


@register(TRACK)
class TrackingRelocalizer(Relocalizer):
    """Tracking from a pose prior with a covariance: landmarks predicted visible, matched in
    covariance windows, PnP, the shared verification; refuses without such a prior."""

    @dataclass(frozen=True)
    class Conf(PnPConf):
        #: Query features matched (a name of ``STEP_FEATURES``); None: ORB where a keyframe
        #: near the prior has ORB landmarks, else SIFT. The query's features are those the
        #: method's own step of that name extracts (ORB's 500, SIFT's 2000, half-size SIFT's
        #: 1000), so a fallback reuses them.
        kind: str | None = None
        #: Query features tracked with when ``kind``'s tracking refuses (a name of
        #: ``STEP_FEATURES``, e.g. ``"sift-half"``: half-size SIFT's coarse keypoints survive
        #: the motion blur of a fast turn that takes ORB's corners); None: none. Off by
        #: default: with 3 good priors per query, "sift-half" tracks 5 of TUM fr1/rpy's 30,
        #: not 2 (there the prior's windows, 5 cm at about 1 m depth, outgrow
        #: ``max_window_fraction`` whatever the features), and 51 of 7-Scenes' 66, not 36,
        #: 11 of the 15 new answers 7-15 cm off.
        fallback: str | None = None
        #: Keyframes nearest the prior (optical axes within ``max_view_angle_deg``) whose
        #: landmarks are projected.
        local_keyframes: int = 10
        max_view_angle_deg: float = 60.0
        #: Probability that the true keypoint of a landmark lies inside its gate
        #: (chi-square, 2 degrees of freedom).
        gate_probability: float = 0.99
        #: Largest gate area, as a share of the image: a window as large as a cell of the
        #: verification's coverage grid (1/16 of the image) is no longer local, so its
        #: landmark is left out; too few left, tracking refuses and the full method runs.
        max_window_fraction: float = 1.0 / 16.0
        #: Best / second-best descriptor distance inside a window (ORB-SLAM's 0.9) and the
        #: quantile of unrelated pairs' distances a match must beat (guided matching's).
        window_ratio: float = 0.9
        background_quantile: float = 0.01
        #: A verified tracked pose must lie within this chi-square gate (6 degrees of
        #: freedom) of the prior, under both covariances: a pose outside it contradicts the
        #: prior it was matched from, and the full method decides.
        prior_gate_probability: float = 0.999
        #: How the pose grows onto the matches found around it: "ransac" solves the window
        #: consensus plus those matches again (P3P LO-RANSAC); "regated" refines from the
        #: solved pose, each match gated by the residual its covariance predicts
        #: (:mod:`..pose.regated_refinement`). "ransac" stays the default: on the room
        #: bench "regated" answered one good-prior draw of 207 outside 5 cm / 5 deg that
        #: "ransac" answered within, for a p50 within the run's noise.
        growth: str = "ransac"
        #: How much better than the prior a tracked pose must be known
        #: (:mod:`..pose.prior_gain`): "every direction": its covariance below the prior's
        #: in the Loewner order; "image average": its inliers' pixel variance below the
        #: prior's on average (lets an answer less certain than the prior along a direction
        #: the pixels hardly see through: 7-Scenes' 6-20 cm answers).
        narrowing: str = "every direction"

        def __post_init__(self) -> None:
            super().__post_init__()
            for name in ("kind", "fallback"):
                value = getattr(self, name)
                if value is not None and value not in STEP_FEATURES:
                    raise ConfigError(f"track: {name} must be one of {sorted(STEP_FEATURES)} "
                                      f"or None, got {value!r}")
            for name in ("gate_probability", "prior_gate_probability", "window_ratio",
                         "max_window_fraction", "background_quantile"):
                if not 0 < getattr(self, name) <= 1:
                    raise ConfigError(f"track: {name} must be in (0, 1], got "
                                      f"{getattr(self, name)}")
            if self.local_keyframes < 1:
                raise ConfigError("track: local_keyframes must be >= 1")
            if self.narrowing not in NARROWING:
                raise ConfigError(f"track: narrowing must be one of {NARROWING}, got "
                                  f"{self.narrowing!r}")
            if self.growth not in GROWTH:
                raise ConfigError(f"track: growth must be one of {GROWTH}, got "
                                  f"{self.growth!r}")

    def __init__(self, kmap: KeyframeMap, conf: TrackingRelocalizer.Conf | None = None,
                 verify_conf: VerifyConf | None = None) -> None:
        super().__init__(kmap)
        self.conf = conf or TrackingRelocalizer.Conf()
        # Tracking always comes before a method that can still answer: where its view
        # cannot check the intrinsics it leaves the query to that method (as a chain's
        # first steps do).
        self.verify_conf = replace(verify_conf or VerifyConf(), trust_unchecked_intrinsics=False)

        # The local maps of the last few keyframe sets: a tracked camera sees the same
        # keyframes for many frames, and pooling their landmarks and weighing them costs as
        # much as matching them. Keyed by map version, so an edited map is pooled afresh.
        # Replaced whole, never changed in place: concurrent queries read it without a lock
        # (only the engine locks), and a race only pools a set once more.
        self._local_maps: dict[tuple[int, tuple[int, ...], str],
                               tuple[LandmarkPool, PointUncertainty]] = {}

    @classmethod
    def from_options(cls, step: MethodStep, kmap: KeyframeMap,
                     options: Mapping[str, Mapping[str, Any]]) -> TrackingRelocalizer:
        return cls(kmap, make_conf(cls.Conf, options.get(TRACK), owner="track"),
                   make_conf(VerifyConf, options.get("verify"), owner="verify"))

    @property
    def method(self) -> str:
        return TRACK

    def add_keyframe(self, keyframe: Keyframe) -> None:
        """Nothing to index: tracking reads the map's landmarks at query time."""

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        """Nothing indexed."""

    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        """The pose tracked from ``prior`` (it must carry a covariance) with the first of the
        query's feature kinds (:meth:`_feature_steps`) that verifies; else NOT_RELOCALIZED
        with each kind's reason."""
        state = self.map.snapshot()
        timings: dict[str, float] = {}
        if prior is None or prior.covariance is None:
            return self._refuse("no prior with a covariance to track from", timings, state)
        near = state.nearest_keyframes(prior.world_from_cam, self.conf.local_keyframes,
                                       self.conf.max_view_angle_deg)
        keyframes = [state.keyframes[k] for k in near]
        steps = _feature_steps(keyframes, self.conf.kind, self.conf.fallback)
        if not steps:
            return self._refuse("no keyframe near the prior has ORB or SIFT landmarks",
                                timings, state)
        reasons: list[str] = []
        for step in steps:
            result = self._track(query, prior, state, near, keyframes, step, timings)
            if result.ok:
                return result
            reasons.append(result.reason if len(steps) == 1 else f"{step}: {result.reason}")
        result.reason = "; ".join(reasons)
        result.timings = timings
        return result

    def _track(self, query: Frame, prior: Prior, state: MapState, near: list[int],
               keyframes: list[Keyframe], step: str, timings: dict[str, float]
               ) -> RelocResult:
        """The pose tracked with the query's ``step`` features (a name of
        ``STEP_FEATURES``), verified, or NOT_RELOCALIZED; its stages' times are added to
        ``timings``."""
        assert prior.covariance is not None
        spec = STEP_FEATURES[step]
        kind = spec["kind"]
        fconf = feature_lib.FeatureConf(kind=kind, max_features=spec["max_features"],
                                        scale=spec.get("query_scale", 1.0))
        # A keypoint of the reduced image is located to one of its pixels: 1 / scale
        # full-image pixels, in the windows and in the solve's weights.
        scale = 1.0 / fconf.scale
        start = time.perf_counter()
        feats = query.features_of(fconf.key, lambda: feature_lib.extract(query.image, fconf))
        start = _add(timings, "features", start)
        pool, uncertainty = self._local_map(state, near, keyframes, kind)
        if len(pool.landmark_ids) == 0:
            return self._refuse("no keyframe near the prior sees what it sees", timings, state)
        gate = float(stats.chi2.ppf(self.conf.gate_probability, 2))
        sigmas = pixel_sigmas(uncertainty, prior.world_from_cam, pool.points_world,
                              query.camera, scale * self.conf.keypoint_sigma_px)
        windows = predict_windows(query.camera, prior.world_from_cam, prior.covariance,
                                  pool.points_world, gate, sigmas)
        width, height = query.camera.size
        local = windows.visible & (windows.area_px <= self.conf.max_window_fraction
                                   * width * height)
        rows = np.flatnonzero(local)
        if len(rows) < self.verify_conf.min_inliers:
            return self._refuse(
                f"prior too uncertain to track: {len(rows)} of {int(windows.visible.sum())} "
                f"predicted landmarks have a window within "
                f"{self.conf.max_window_fraction:.3g} of the image", timings, state)
        # The distance unrelated pairs of these descriptors fall below by chance: the same
        # for the windows' matches and the guided ones around the solved pose, so drawn once.
        background = background_distance(feats.descriptors, pool.descriptors,
                                         self.conf.background_quantile)
        q_idx, m_rows = match_in_windows(
            feats, windows, rows, pool.descriptors, gate, ratio=self.conf.window_ratio,
            background_quantile=self.conf.background_quantile, background=background)
        start = _add(timings, "track_match", start)
        solved = solve_pnp_indexed(feats.keypoints_px[q_idx], pool.points_world[m_rows],
                                   query.camera, self.conf, uncertainty=uncertainty.take(m_rows),
                                   keypoint_scales=_scales(scale, len(q_idx)))
        start = _add(timings, "solve", start)
        if solved is None:
            return self._refuse(f"no pose from {len(q_idx)} matches in the prior's windows",
                                timings, state, num_matches=len(q_idx))
        est, inliers = solved
        seed = (len(q_idx), int(est.inliers or 0))
        chance = _window_chance(est, windows.area_px[m_rows])
        grown = self._grow(query, feats, est, pool, q_idx[inliers], m_rows[inliers],
                           uncertainty, scale, background)
        start = _add(timings, "guided", start)
        if grown is not None:
            est, q_idx, m_rows, inliers = grown
        est.keyframe_ids = pool.keyframes_of(m_rows[inliers], near)
        est.inlier_keypoints = q_idx[inliers]
        est.inlier_landmark_ids = pool.landmark_ids[m_rows[inliers]]
        # The false-alarm test judges the consensus found in the prior's windows, against
        # the chance of agreeing inside a window; what guided matching added around the
        # solved pose agrees with it by construction.
        est.unguided_evidence = seed
        self._widen_for_keyframes(est, feats.keypoints_px[q_idx[inliers]],
                                  pool.points_world[m_rows[inliers]], query,
                                  pool.keyframe_rows[m_rows[inliers]])
        est.chance_probability = max(est.chance_probability or 0.0, chance)
        self._limit_focal_starts(est, prior, pool.points_world[m_rows[inliers]])
        start = time.perf_counter()
        est = settle_pose_errors(est, state, kind, self.conf, est.inlier_landmark_ids)
        result = result_from_estimate(est, self.verify_conf, method=TRACK,
                                      map_version=state.version, timings=timings)
        _add(timings, "verify", start)
        if result.ok and not _within_prior(est, result, prior, self.conf.prior_gate_probability):
            return self._refuse("the tracked pose lies outside the prior's gate", timings, state,
                                num_matches=len(q_idx), inliers=int(est.inliers or 0))
        if result.ok and not self._narrows(query, est, pool.points_world[m_rows[inliers]],
                                           prior.covariance):
            # Where this image (its matches and its camera) fixes the pose less well than
            # the prior (along some direction, or for its inliers' pixels on average), the
            # windows chose the matches: the method, which matches without the prior,
            # decides. The keyframes' pose errors, in the answer's stated covariance, are
            # left out: a prior anchored to this map (the ROS 2 map_from_odom) holds them too.
            return self._refuse(f"the tracked pose is known no better than the prior "
                                f"({self.conf.narrowing})", timings, state,
                                num_matches=len(q_idx), inliers=int(est.inliers or 0))
        if result.ok and narrow_support(est, self.verify_conf):
            # A pose fixed by a small area of the image is weakly conditioned: the method,
            # which weighs such answers against the rest of the map, decides.
            return self._refuse("the tracked pose rests on a small part of the image", timings,
                                state, num_matches=len(q_idx), inliers=int(est.inliers or 0))
        return result

    def _narrows(self, query: Frame, est: PoseEstimate, inliers_world: Array,
                 prior_covariance: Array) -> bool:
        """Whether ``est`` is better known than the prior (``Conf.narrowing``)."""
        if self.conf.narrowing == "every direction":
            return narrower_everywhere(est.covariance, prior_covariance)
        return narrows_prior(query.camera, est.world_from_cam, inliers_world, est.covariance,
                             prior_covariance)

    def _grow(self, query: Frame, feats: Features, est: PoseEstimate, pool: LandmarkPool,
              seed_q: IntArray, seed_rows: IntArray, uncertainty: PointUncertainty,
              scale: float, background: float
              ) -> tuple[PoseEstimate, IntArray, IntArray, IntArray] | None:
        """The pose solved again or refined (``Conf.growth``) on the window consensus
        (``seed_q``, ``seed_rows``) plus the landmarks matched around the solved pose
        (windows of twice the inlier threshold, :func:`..pose.prior_windows.search_around`):
        the prior's windows are wide, and a crowd of similar descriptors hides matches that
        the solved pose's narrow windows find. ``scale``: the query keypoints' localisation
        in full-image pixels; ``background``: the descriptors' chance distance at
        ``Conf.background_quantile``, reused where guided matching's quantile is that one.
        (estimate, query indices, pool rows, inlier indices), or None when that adds no
        inlier."""
        guided = GuidedConf()
        same = guided.background_quantile == self.conf.background_quantile
        g_idx, g_rows = search_around(
            feats, query.camera, est.world_from_cam, pool.descriptors, pool.points_world,
            guided.window_factor * self.conf.max_reproj_error_px, ratio=guided.window_ratio,
            background_quantile=guided.background_quantile,
            background=background if same else None)
        q_all, rows_all = union_matches(seed_q, seed_rows, g_idx, g_rows)
        px, points = feats.keypoints_px[q_all], pool.points_world[rows_all]
        if self.conf.growth == "regated":
            # Each correspondence gated by the residual the solved pose's covariance predicts
            # for it: a fixed inlier threshold can leave out the right guided matches where
            # the window consensus did not reach, and keep that pose in its own basin.
            solved = refine_from(est, px, points, query.camera, self.conf,
                                 uncertainty.take(rows_all),
                                 float(stats.chi2.ppf(self.conf.gate_probability, 2)))
        else:
            # A RANSAC again, not a refinement at the inlier threshold from the solved pose:
            # that pose rests on the window consensus alone, and at its inlier threshold it
            # can leave out the right guided matches and settle in its own basin
            # (centimetres off on the synthetic room).
            solved = solve_pnp_indexed(px, points, query.camera, self.conf,
                                       uncertainty=uncertainty.take(rows_all),
                                       keypoint_scales=_scales(scale, len(q_all)))
        if solved is None or (solved[0].inliers or 0) <= (est.inliers or 0):
            return None
        return solved[0], q_all, rows_all, solved[1]

    def _local_map(self, state: MapState, near: list[int], keyframes: list[Keyframe],
                   kind: str) -> tuple[LandmarkPool, PointUncertainty]:
        """The pool of ``kind`` landmarks of keyframes ``near`` and their widened depth
        uncertainty (:func:`_landmark_uncertainty`), kept for the last
        :data:`LOCAL_MAPS_KEPT` keyframe sets of the map's version."""
        key = (state.version, tuple(near), kind)
        kept = self._local_maps.get(key)
        if kept is not None:
            return kept
        pool = LandmarkPool.gather(keyframes, kind)
        made = pool, _landmark_uncertainty(pool, state, near, keyframes)
        # the last LOCAL_MAPS_KEPT sets made, oldest first
        self._local_maps = dict([*self._local_maps.items(), (key, made)][-LOCAL_MAPS_KEPT:])
        return made

    @staticmethod
    def _widen_for_keyframes(est: PoseEstimate, inlier_px: Array, inliers_world: Array,
                             query: Frame, source_keyframes: IntArray) -> None:
        """Widen ``est``'s covariance to the spread its inliers' source keyframes show
        (:mod:`..pose.cluster_covariance`): the landmarks are pooled from several
        keyframes, and each group shares its keyframe's pose error, which the model
        covariance of independent residuals does not see."""
        if est.covariance is None:
            return
        robust = cluster_robust_covariance(est.world_from_cam, inlier_px, inliers_world,
                                           query.camera, source_keyframes)
        if robust is not None:
            est.covariance = at_least(est.covariance, robust)

    def _limit_focal_starts(self, est: PoseEstimate, prior: Prior, inliers_world: Array
                            ) -> None:
        """Start ``est``'s intrinsics test only from the focals the prior's gate leaves open
        (:mod:`..pose.prior_focal`): a focal error the gate excludes needs no search."""
        if est.intrinsics_test is None or prior.covariance is None or len(inliers_world) == 0:
            return
        depth = float(np.median(transform_points(invert(est.world_from_cam),
                                                 inliers_world)[:, 2]))
        reach = focal_reach(axis_variance(prior.covariance, est.covariance), depth,
                            float(stats.chi2.ppf(self.conf.prior_gate_probability, 6)))
        # The test is pnp's, which takes its focal starts by keyword.
        test: Callable[..., IntrinsicsCheck | None] = est.intrinsics_test
        est.intrinsics_test = functools.partial(test, focal_starts=focal_starts_within(reach))

    def _refuse(self, reason: str, timings: dict[str, float], state: MapState,
                **evidence: Any) -> RelocResult:
        return RelocResult.failure(TRACK, reason, timings=timings, map_version=state.version,
                                   **evidence)


def _landmark_uncertainty(pool: LandmarkPool, state: MapState, keyframe_ids: list[int],
                          keyframes: list[Keyframe]) -> PointUncertainty:
    """The depth uncertainty of every pool landmark, widened by its keyframe's pose error
    (:mod:`..pose.landmark_keyframe_errors`): the landmarks are pooled from several
    keyframes, so a depth that the keypoints alone fix well but a keyframe's pose error
    moves would pull the pooled pose towards that keyframe's error."""
    rows = np.arange(len(pool.landmark_ids))
    rot, pos = keyframe_pose_sigmas(state, keyframe_ids)
    focal = np.array([kf.camera.fx for kf in keyframes], np.float64)
    return widen_for_keyframe_errors(pool.uncertainty(state, keyframes, rows),
                                     pool.points_world, pool.keyframe_rows, rot, pos, focal)


def _feature_steps(keyframes: list[Keyframe], kind: str | None, fallback: str | None
                   ) -> list[str]:
    """The query features to track with, in order (names of ``STEP_FEATURES``): ``kind``, or
    ORB where a keyframe of ``keyframes`` has ORB landmarks (the cheap path), else SIFT where
    one has SIFT landmarks; then ``fallback`` where one has its kind of landmarks."""
    first = kind or next((k for k in ("orb", "sift") if _has_landmarks(keyframes, k)), None)
    steps = [] if first is None else [first]
    if (fallback is not None and fallback != first
            and _has_landmarks(keyframes, STEP_FEATURES[fallback]["kind"])):
        steps.append(fallback)
    return steps


def _has_landmarks(keyframes: list[Keyframe], kind: str) -> bool:
    """Whether a keyframe of ``keyframes`` has ``kind`` features with landmarks."""
    for kf in keyframes:
        feats = kf.features.get(kind)
        if feats is not None and bool(np.any(feats.landmark_ids >= 0)):
            return True
    return False


def _add(timings: dict[str, float], stage: str, start: float) -> float:
    """Add the time since ``start`` to ``timings[stage]`` (a query may track with several
    kinds of features); the time now, the next stage's start."""
    now = time.perf_counter()
    timings[stage] = timings.get(stage, 0.0) + now - start
    return now


def _scales(scale: float, n: int) -> Array | None:
    """(n,) keypoint localisation scales of features found on an image reduced by
    ``1 / scale``; None (one pixel each) at full size."""
    return None if scale == 1 else np.full(n, scale)


def _window_chance(est: PoseEstimate, areas_px: Array) -> float:
    """The probability that a wrong match agrees with a pose by chance when each match was
    drawn from its window rather than from the whole image: ``pi t^2 / area`` (at most 1)
    averaged over the matches. The binomial with this mean bounds the tail of the
    matches' Poisson-binomial count beyond its mean (Hoeffding 1956), which is what the
    false-alarm test reads."""
    t = est.inlier_threshold_px
    if t is None or len(areas_px) == 0:
        return 0.0
    return float(np.mean(np.minimum(np.pi * t * t / np.maximum(areas_px, 1e-12), 1.0)))


def _within_prior(est: PoseEstimate, result: RelocResult, prior: Prior, probability: float
                  ) -> bool:
    """Whether the answer lies inside the prior's ``probability`` gate: the twist from the
    prior to the answer, Mahalanobis under the sum of both covariances, within
    ``chi2_6(probability)``."""
    assert prior.covariance is not None and result.world_from_cam is not None
    xi = se3_log(invert(prior.world_from_cam) @ result.world_from_cam)
    own = result.covariance if result.covariance is not None else est.covariance
    total = np.asarray(prior.covariance, np.float64) + (0.0 if own is None else own)
    try:
        m2 = float(xi @ np.linalg.solve(total, xi))
    except np.linalg.LinAlgError:
        m2 = float(xi @ np.linalg.pinv(total) @ xi)
    return m2 <= float(stats.chi2.ppf(probability, 6))


def relocalize_with_prior(relocalizer: Relocalizer, tracker: Relocalizer | None,
                          query: Frame, *, prior: Prior | None = None,
                          hypotheses: int = 1) -> RelocResult:
    """``tracker``'s answer when ``prior`` carries a covariance and tracking verifies; else
    ``relocalizer``'s (the method asked), with tracking's time summed into its timings and
    its reason prefixed to a refusal's."""
    if (tracker is None or prior is None or prior.covariance is None
            or relocalizer.method == TRACK):
        return relocalizer.relocalize(query, prior=prior, hypotheses=hypotheses)
    tracked = tracker.relocalize(query, prior=prior, hypotheses=hypotheses)
    if tracked.ok:
        return tracked
    result = relocalizer.relocalize(query, prior=prior, hypotheses=hypotheses)
    for stage, seconds in tracked.timings.items():
        key = stage if stage not in ("features", "verify", "solve") else f"track_{stage}"
        result.timings[key] = result.timings.get(key, 0.0) + seconds
    if not result.ok:
        result.reason = f"{TRACK}: {tracked.reason}; {result.reason}"
    return result
