"""Localization with a prior (``"track"``): a query that comes with a pose prior and its
covariance (a VIO's pose composed with ``map_from_odom``) is a tracking problem. The
landmarks of the keyframes that see what the prior sees are projected with the prior, each
is matched only to the query keypoints inside the chi-square gate of its projection's
covariance (:mod:`..pose.prior_windows`), then PnP LO-RANSAC with refinement and the
shared verification (:func:`.base.result_from_estimate`), unchanged but for the chance
model: a wrong match was drawn from its window, not from the whole image.

:func:`.tracking_fallback.relocalize_with_prior` runs it before any method when the prior
carries a covariance and falls back to that method when tracking does not verify. The local
map it matches against is :mod:`.tracking_local_map`'s, the growth of a solved pose onto
the matches around it :mod:`.tracking_growth`'s."""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core import distributions as stats
from ...core import features as feature_lib
from ...core.errors import ConfigError
from ...core.frame import Frame, Keyframe
from ...core.map import KeyframeMap, MapState
from ...core.methods import MethodStep
from ...core.plugins import make_conf
from ..pose.base import PoseEstimate
from ..pose.guided import background_distance
from ..pose.map_consistency import settle_pose_errors
from ..pose.pnp import solve_pnp_indexed
from ..pose.pnp_conf import PnPConf
from ..pose.prior_focal import limit_focal_starts
from ..pose.prior_gain import narrower_everywhere, narrows_prior, stated_and_unique
from ..pose.prior_gate import within_prior
from ..pose.prior_windows import (
    match_in_windows,
    pixel_sigmas,
    predict_windows,
    window_chance,
)
from .base import (
    Prior,
    Relocalizer,
    RelocResult,
    VerifyConf,
    note_map_calibration,
    register,
    result_from_estimate,
)
from .chain_hooks import narrow_support
from .multi import STEP_FEATURES
from .tracking_growth import GROWTH, grow, keypoint_scales
from .tracking_local_map import LocalMaps, feature_steps, widen_for_source_keyframes

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: The method name a tracked answer carries (``RelocResult.method``).
TRACK = "track"
#: How a tracked pose must narrow its prior (``Conf.narrowing``).
NARROWING = ("every direction", "stated, unique", "image average")


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
        #: (:mod:`..pose.prior_gain`): "stated, unique": the covariance it states relative to
        #: the map, plus the farthest solution its data cannot exclude as a variance, below
        #: the prior's in the Loewner order; "every direction": the decision covariance (the
        #: intrinsics free, the calibration doubted) below the prior's; "image average": its
        #: inliers' pixel variance below the prior's on average (lets an answer less
        #: certain than the prior along a direction the pixels hardly see through:
        #: 7-Scenes' 6-20 cm answers). "stated, unique" is the default: with the bench's
        #: good priors it tracks Strecha fountain 6 of 15 draws and herzjesu 13 of 24 (0
        #: and 0 with "every direction": their decision covariance holds the doubted
        #: calibration's 5-10 cm along the optical axis of a facade ~10 m away), 0.5-1.5 cm
        #: off, and still refuses the 6 tracked 7-Scenes answers 5-20 cm off (their farthest
        #: unexcluded solution lies 1.1-3.4 prior sigmas away) and TUM's two 9-11 cm ones.
        narrowing: str = "stated, unique"

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

        # The local maps of the last few keyframe sets (:mod:`.tracking_local_map`).
        self._local_maps = LocalMaps()

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
        query's feature kinds (:func:`.tracking_local_map.feature_steps`) that verifies; else NOT_RELOCALIZED
        with each kind's reason."""
        state = self.map.snapshot()
        timings: dict[str, float] = {}
        if prior is None or prior.covariance is None:
            return self._refuse("no prior with a covariance to track from", timings, state)
        near = state.nearest_keyframes(prior.world_from_cam, self.conf.local_keyframes,
                                       self.conf.max_view_angle_deg)
        keyframes = [state.keyframes[k] for k in near]
        steps = feature_steps(keyframes, self.conf.kind, self.conf.fallback)
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
        pool, uncertainty = self._local_maps.get(state, near, keyframes, kind)
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
                                   keypoint_scales=keypoint_scales(scale, len(q_idx)))
        start = _add(timings, "solve", start)
        if solved is None:
            return self._refuse(f"no pose from {len(q_idx)} matches in the prior's windows",
                                timings, state, num_matches=len(q_idx))
        est, inliers = solved
        seed = (len(q_idx), int(est.inliers or 0))
        chance = window_chance(est.inlier_threshold_px, windows.area_px[m_rows])
        grown = grow(query, feats, est, pool, q_idx[inliers], m_rows[inliers], uncertainty,
                     pnp_conf=self.conf, growth=self.conf.growth,
                     gate_probability=self.conf.gate_probability,
                     background_quantile=self.conf.background_quantile, scale=scale,
                     background=background)
        start = _add(timings, "guided", start)
        if grown is not None:
            est, q_idx, m_rows, inliers = grown
        inlier_rows = m_rows[inliers]
        inliers_world = pool.points_world[inlier_rows]
        est.keyframe_ids = pool.keyframes_of(inlier_rows, near)
        est.inlier_keypoints = q_idx[inliers]
        est.inlier_landmark_ids = pool.landmark_ids[inlier_rows]
        # The false-alarm test judges the consensus found in the prior's windows, against
        # the chance of agreeing inside a window; what guided matching added around the
        # solved pose agrees with it by construction.
        est.unguided_evidence = seed
        widen_for_source_keyframes(est, feats.keypoints_px[q_idx[inliers]], inliers_world,
                                   query, pool.keyframe_rows[inlier_rows])
        est.chance_probability = max(est.chance_probability or 0.0, chance)
        limit_focal_starts(est, prior.covariance, inliers_world,
                           float(stats.chi2.ppf(self.conf.prior_gate_probability, 6)))
        start = time.perf_counter()
        est = settle_pose_errors(est, state, kind, self.conf, est.inlier_landmark_ids)
        # As every chain step does: an answer of a query that claims the map's own camera
        # states its covariance under the map's calibration accuracy, so a tracked answer
        # and the method's state the same for the same geometry.
        note_map_calibration(est, query.camera, state)
        result = result_from_estimate(est, self.verify_conf, method=TRACK,
                                      map_version=state.version, timings=timings)
        _add(timings, "verify", start)
        if result.ok and not self._within_prior(est, result, prior):
            return self._refuse("the tracked pose lies outside the prior's gate", timings, state,
                                num_matches=len(q_idx), inliers=int(est.inliers or 0))
        if result.ok and not self._narrows(query, est, result, inliers_world, prior.covariance):
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

    def _narrows(self, query: Frame, est: PoseEstimate, result: RelocResult,
                 inliers_world: Array, prior_covariance: Array) -> bool:
        """Whether ``est`` (answered as ``result``) is better known than the prior
        (``Conf.narrowing``)."""
        if self.conf.narrowing == "every direction":
            return narrower_everywhere(est.covariance, prior_covariance)
        if self.conf.narrowing == "stated, unique":
            if result.covariance is None:
                return False
            own = np.asarray(result.covariance, np.float64)
            if est.map_covariance is not None:
                own = own - est.map_covariance
            far = None if est.intrinsics is None else est.intrinsics.unexcluded_twist
            return narrower_everywhere(
                stated_and_unique(own, far, bool(est.query_camera_is_map_calibration)),
                prior_covariance)
        return narrows_prior(query.camera, est.world_from_cam, inliers_world, est.covariance,
                             prior_covariance)

    def _within_prior(self, est: PoseEstimate, result: RelocResult, prior: Prior) -> bool:
        """Whether the answer lies inside the prior's gate (:mod:`..pose.prior_gate`) under
        its stated covariance (the estimate's where the answer states none)."""
        assert prior.covariance is not None and result.world_from_cam is not None
        own = result.covariance if result.covariance is not None else est.covariance
        return within_prior(result.world_from_cam, own, prior.world_from_cam,
                            prior.covariance, self.conf.prior_gate_probability)

    def _refuse(self, reason: str, timings: dict[str, float], state: MapState,
                **evidence: Any) -> RelocResult:
        return RelocResult.failure(TRACK, reason, timings=timings, map_version=state.version,
                                   **evidence)


def _add(timings: dict[str, float], stage: str, start: float) -> float:
    """Add the time since ``start`` to ``timings[stage]`` (a query may track with several
    kinds of features); the time now, the next stage's start."""
    now = time.perf_counter()
    timings[stage] = timings.get(stage, 0.0) + now - start
    return now
