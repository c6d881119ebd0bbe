"""Five-point pose finder (thesis: "the five-point algorithm can then be used to find the
scaled 6 DoF transformation"): the query's pose from its epipolar geometry with two or more
keyframes of known pose, for keyframes with few or no landmarks (rotations, tiny baselines).

Per candidate keyframe: the query's SIFT matched to *all* its keypoints (Lowe 0.8), as ideal
pinhole pixels and bearings; PoseLib five-point LO-RANSAC (``kf_from_query``, unit
translation) and a two-point Kabsch LO-RANSAC (rotation only); Torr's GRIC (1998) picks the
model: a *rotation pair* shows no measurable parallax. Pairs chance could explain (ORSA) go.
Initial pose: chordal mean of the rotations; the centre at the rotation pairs' keyframes, else
where the rays ``C_k + s d_k`` meet, else on the one ray at its landmarks' scale; with enough
landmarks the three-point pose is one more hypothesis. Gauss-Newton on the query's right twist
(keyframes fixed) over all pairs at once (:func:`.fivept_refine.pair_blocks`); covariance ``(J^T J)^-1`` of
the whitened residuals: infinite or huge where the position is free (one ray and no landmark,
collinear rays, a rotation and no scene distance), so the shared verification refuses it.
"""

from __future__ import annotations

import dataclasses
import time
from typing import ClassVar

import numpy as np
import numpy.typing as npt
import poselib

from ...core import features as feature_lib
from ...core.cameras import Camera
from ...core.errors import ConfigError
from ...core.frame import Features, Frame, Keyframe
from ...core.geometry import invert
from ...core.map import MapState
from ..place.base import PlaceCandidate
from . import fivept_refine as refine
from . import fivept_twoview as twoview
from .base import PoseEstimate, PoseFinder, log10_false_alarms, register
from .fivept_refine import Pair
from .map_uncertainty import keyframes_covariance

Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]
#: A rotation fits its data to 2 sigma^2 per point plus half the squared parallax p, the
#: general model to sigma^2 for ln 4 more per point: GRIC keeps the rotation while
#: mean p^2 < 2 (ln 4 - 1) sigma^2. That RMS parallax, in sigmas, hides in the noise.
_HIDDEN_PARALLAX = float(np.sqrt(2 * (np.log(twoview.GRIC_R) - 1)))
#: Largest expected number of false alarms of a pair's consensus (a-contrario, ORSA): the
#: 1 % wrong-pose budget of the shared verification.
_MAX_FALSE_ALARMS = 1e-2
#: Fewest landmark matches used (the shared verification's floor): below it their residual
#: RMS, which weighs them, is itself unreliable (relative error > 19 %).
_MIN_LANDMARKS = 10


@register("5pt")
class FivePointPoseFinder(PoseFinder):
    """Relative poses (five-point or rotation) to several candidate keyframes, chained into
    one metric pose of the query."""

    pools_candidates: ClassVar[bool] = True
    reads_unmapped_keypoints: ClassVar[bool] = True   # relative poses from 2D-2D matches

    @dataclasses.dataclass(frozen=True)
    class Conf:
        kind: str = "sift"
        max_features: int = 2000
        ratio: float = 0.8           # Lowe's ratio (thesis 3.1.3)
        max_keyframes: int = 3       # candidate keyframes used (the first with support)
        #: Keypoint localisation noise of the inlier gates, pixels (before it is estimated).
        keypoint_sigma_px: float = 1.0
        #: Floor of the estimated noise (keypoints are not more precise than this).
        min_sigma_px: float = 0.25
        #: Upper bound of the scene's distance for rotation pairs without landmarks, metres
        #: (e.g. the room's size); None: unknown, so a rotation alone gives no position.
        assumed_depth_m: float | None = None
        refine_iterations: int = 10
        min_iterations: int = 100
        max_iterations: int = 10000
        success_prob: float = 0.9999
        seed: int = 0

        def __post_init__(self) -> None:
            feature_lib.FeatureConf(kind=self.kind, max_features=self.max_features)
            if not (0 < self.ratio <= 1 and self.max_keyframes >= 1 and self.min_sigma_px >= 0
                    and self.keypoint_sigma_px > 0 and self.refine_iterations >= 0
                    and (self.assumed_depth_m is None or self.assumed_depth_m > 0)
                    and 0 < self.min_iterations <= self.max_iterations
                    and 0 < self.success_prob < 1):
                raise ConfigError(
                    "5pt: expected 0 < ratio <= 1, max_keyframes >= 1, keypoint_sigma_px > 0, "
                    "min_sigma_px >= 0, refine_iterations >= 0, assumed_depth_m > 0 or None, "
                    f"0 < min_iterations <= max_iterations, 0 < success_prob < 1; got {self}")

    def __init__(self, conf: FivePointPoseFinder.Conf) -> None:
        super().__init__(conf)
        self.conf: FivePointPoseFinder.Conf = conf
        self.required_features = frozenset({conf.kind})

    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        """Pose from the first ``max_keyframes`` candidates with support; with none, the best
        keyframe's pose with zero inliers (refused); None if no candidate is in ``state``."""
        keyframes = [state.keyframes[c.keyframe_id] for c in candidates
                     if c.keyframe_id in state.keyframes]
        if not keyframes:
            return None
        timings = {"match": 0.0, "solve": 0.0}
        feats = self.query_features(query, timings)
        pairs: list[Pair] = []
        num_matches = 0
        for kf in keyframes:
            if len(pairs) == self.conf.max_keyframes:
                break
            start = time.perf_counter()
            matches = self._match(feats, kf)
            timings["match"] += time.perf_counter() - start
            start = time.perf_counter()
            pair = None if matches is None else self._fit_pair(query.camera, kf, *matches)
            timings["solve"] += time.perf_counter() - start
            num_matches += 0 if matches is None else len(matches[0])
            pairs += [] if pair is None else [pair]
        if not pairs:
            return PoseEstimate(world_from_cam=keyframes[0].world_from_cam.copy(),
                                keyframe_ids=[kf.id for kf in keyframes], num_matches=num_matches,
                                inliers=0, timings=timings)
        start = time.perf_counter()
        est = self._solve(pairs, state)
        timings["solve"] += time.perf_counter() - start
        est.num_matches, est.timings = num_matches, timings
        return est

    def feature_confs(self) -> dict[str, feature_lib.FeatureConf]:
        return {self.conf.kind: feature_lib.FeatureConf(kind=self.conf.kind,
                                                        max_features=self.conf.max_features)}

    def _match(self, feats: Features, keyframe: Keyframe) -> tuple[Array, Array, Array] | None:
        """Ratio-test matches to *all* the keyframe's keypoints: query pixels, keyframe
        pixels and landmarks. SIFT repeats a keypoint with several orientations: one match
        per keyframe place, then per query place, the nearest (no double counting)."""
        kf_feats = keyframe.features.get(self.conf.kind)
        if kf_feats is None:
            return None
        q, k, dist = feature_lib.match_ratio(feats.descriptors, kf_feats.descriptors,
                                             ratio=self.conf.ratio)
        for keypoints_px, side in ((kf_feats.keypoints_px, 1), (feats.keypoints_px, 0)):
            px = keypoints_px[(q, k)[side]]
            order = np.lexsort((dist, *px.T))
            keep = np.sort(order[np.unique(px[order], axis=0, return_index=True)[1]])
            q, k, dist = q[keep], k[keep], dist[keep]
        return feats.keypoints_px[q], kf_feats.keypoints_px[k], kf_feats.points_world[k]

    def _fit_pair(self, q_cam: Camera, kf: Keyframe, q_raw: Array, k_raw: Array,
                  k_world: Array) -> Pair | None:
        """Both models by RANSAC and GRIC's choice; None if chance could explain it."""
        c, k_cam = self.conf, kf.camera
        q_px, k_px = q_cam.undistort_pixels(q_raw), k_cam.undistort_pixels(k_raw)
        ok = np.isfinite(q_px).all(1) & np.isfinite(k_px).all(1)
        n, f = int(ok.sum()), twoview.focal(k_cam)
        if n < 6:  # a five-point sample and one match to check it
            return None
        q_b, k_b = twoview.bearings(q_cam, q_px[ok]), twoview.bearings(k_cam, k_px[ok])
        ransac = {"max_epipolar_error": refine.GATE_1D * c.keypoint_sigma_px, "seed": c.seed,
                  "min_iterations": c.min_iterations, "max_iterations": c.max_iterations,
                  "success_prob": c.success_prob}
        pose, info = poselib.estimate_relative_pose(q_px[ok], k_px[ok], twoview.ideal(q_cam),
                                                    twoview.ideal(k_cam), ransac, {})
        general = np.eye(4)
        general[:3, :] = pose.Rt  # PoseLib's pose maps query points into the keyframe
        e_inl = np.asarray(info["inliers"], bool)
        rot = twoview.rotation_ransac(q_b, k_b, f,
                                      refine.GATE_2D * np.sqrt(2) * c.keypoint_sigma_px,
                                      e_inl.mean(), c)
        e_gen = twoview.epipolar_px(general, q_b, k_b, f)
        e_rot = twoview.transfer(rot, q_b, k_b, f) / np.sqrt(2)  # as a distance in 4-D
        # Noise from the general model's inliers (the median of |N(0, s^2)| is 0.674 s).
        sigma = max(c.min_sigma_px, 1.4826 * float(np.median(np.abs(e_gen[e_inl])))
                    if e_inl.any() else c.keypoint_sigma_px)
        rotation = twoview.gric(e_rot, sigma, 2, 3) < twoview.gric(e_gen, sigma, 3, 5)
        gate = (refine.GATE_2D if rotation else refine.GATE_1D) * c.keypoint_sigma_px
        inliers = (e_rot if rotation else np.abs(e_gen)) < gate
        # Chance that a random keyframe point lies within the gate: a disc of the transfer
        # gate (rotation), or the band along an epipolar line at most the diagonal long.
        area = np.pi * 2 * gate**2 if rotation else 2 * gate * np.hypot(*k_cam.size)
        p = min(area / (k_cam.width * k_cam.height), 1.0)
        if log10_false_alarms(n, int(inliers.sum()), 2 if rotation else 5, p) > np.log10(
                _MAX_FALSE_ALARMS):
            return None
        # Parallax: the inliers' transfer RMS beyond its noise (2 images x 2 axes).
        parallax = np.sqrt(max(2 * np.mean(e_rot[inliers] ** 2) - 4 * sigma**2, 0.0))
        kf_from_query = np.eye(4)
        kf_from_query[:3] = np.column_stack([rot, np.zeros(3)]) if rotation else general[:3]
        return Pair(kf, q_cam, q_raw[ok], q_px[ok], q_b, k_b, k_world[ok], kf_from_query,
                     bool(rotation), inliers, sigma, p,
                     max(float(parallax), _HIDDEN_PARALLAX * sigma))

    def _refine(self, pairs: list[Pair], pose: Array, masks: tuple[Mask, ...] | None = None
                ) -> tuple[float, Array, tuple[Mask, ...], tuple[Array, ...]]:
        """Joint Gauss-Newton from ``pose``, inliers re-selected after it: (MSAC score, pose,
        inlier masks and errors per pair)."""
        sigma = self.conf.keypoint_sigma_px
        if masks is None:  # landmarks may be badly triangulated: those fitting ``pose`` only
            masks = tuple(p.inliers & (refine.inliers(p, pose, sigma)[0] | ~p.has_landmark)
                          for p in pairs)
        blocks = [b for p, m in zip(pairs, masks, strict=True)
                  for b in refine.pair_blocks(p, m, pose, self.conf.assumed_depth_m)]
        pose = refine.gauss_newton(blocks, pose, self.conf.refine_iterations)
        masks, errs = zip(*(refine.inliers(p, pose, sigma) for p in pairs), strict=True)
        gates = [np.where(p.has_landmark | p.rotation, refine.GATE_2D, refine.GATE_1D) * sigma for p in pairs]
        capped = [np.minimum(e, g) for e, g in zip(errs, gates, strict=True)]
        return sum(float(e @ e) for e in capped), pose, masks, errs

    def _solve(self, pairs: list[Pair], state: MapState) -> PoseEstimate:
        """The best hypothesis refined (MSAC score), its covariance and evidence; the pose
        rests on the keyframes' poses (their rays), each by its share of the inliers, so
        their covariances move to it (:func:`.map_uncertainty.keyframes_covariance`)."""
        c = self.conf
        # Landmarks carry triangulation errors, not keypoint noise: they take part only
        # where the rays leave the scale free, and only enough of them. Then the three-point
        # pose (thesis: "if depth is known") is a hypothesis too: it also settles the
        # two-fold five-point ambiguity of a plane.
        landmarks = sum(int((p.inliers & p.has_landmark).sum()) for p in pairs)
        landmark_pose = (_three_point_pose(pairs, refine.GATE_2D * np.sqrt(2) * c.keypoint_sigma_px, c)
                         if landmarks >= _MIN_LANDMARKS else None)
        if sum(not p.rotation for p in pairs) >= 2 or landmarks < _MIN_LANDMARKS:
            pairs = [dataclasses.replace(p, k_world=np.full_like(p.k_world, np.nan)) for p in pairs]
        inits = _initial_poses(pairs) + ([] if landmark_pose is None else [landmark_pose])
        _, pose, masks, _ = min((self._refine(pairs, init) for init in inits), key=lambda r: r[0])
        _, pose, masks, errs = self._refine(pairs, pose, masks)  # the winner, once more
        blocks = [b for p, m in zip(pairs, masks, strict=True)
                  for b in refine.pair_blocks(p, m, pose, c.assumed_depth_m)]
        errors = np.concatenate([e[m] for e, m in zip(errs, masks, strict=True)])
        counts = np.array([m.sum() for m in masks])
        order = np.argsort(counts, kind="stable")[::-1]
        return PoseEstimate(
            world_from_cam=pose, keyframe_ids=[pairs[i].keyframe.id for i in order if counts[i]],
            inliers=len(errors),
            reprojection_rms_px=float(np.sqrt(np.mean(errors**2))) if len(errors) else None,
            covariance=refine.covariance(blocks, pose) * refine.shared_noise_factor(pairs, masks),
            map_covariance=keyframes_covariance(pose, state, [p.keyframe.id for p in pairs],
                                                counts),
            inlier_px=np.concatenate([p.q_raw[m] for p, m in zip(pairs, masks, strict=True)]),
            image_size=pairs[0].q_cam.size,
            # For the a-contrario test: the gate, every pair's minimal sample (the joint pose
            # rests on all of them), the chance agreement of a match (bands, discs).
            inlier_threshold_px=(refine.GATE_2D if all(p.rotation for p in pairs) else refine.GATE_1D)
            * c.keypoint_sigma_px,
            sample_size=sum(2 if p.rotation else 5 for p, k in zip(pairs, counts, strict=True) if k),
            chance_probability=float(np.average([p.chance for p in pairs], weights=counts + 1e-9)))


# -- the query's pose --------------------------------------------------------------------------
def _initial_poses(pairs: list[Pair]) -> list[Array]:
    """Inlier-weighted chordal mean of the rotations, and the centre at the rotation pairs'
    keyframes; else where the rays meet in front of their keyframes; else (nearly parallel
    rays: a tight cluster of keyframes, collinear ones) starts along the mean ray 1 to 30
    times the cluster's size out; one ray: at its landmarks' scale (1 m without any: any
    scale fits one ray, and the covariance says so)."""
    weights = np.array([p.inliers.sum() for p in pairs], float)
    world_from_query = [p.keyframe.world_from_cam @ p.kf_from_query for p in pairs]
    u, _, vt = np.linalg.svd(sum(w * t[:3, :3] for w, t in zip(weights, world_from_query,
                                                                strict=True)))
    out = np.eye(4)
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    centres = np.stack([p.keyframe.position_world for p in pairs])
    rays = np.stack([t[:3, 3] for t in world_from_query]) - centres
    rot = np.array([p.rotation for p in pairs])
    if rot.any():
        starts = [np.average(centres[rot], axis=0, weights=weights[rot])]
    elif len(pairs) == 1:
        starts = [centres[0] + rays[0] * _landmark_scale(pairs[0], rays[0], out[:3, :3])]
    else:  # min sum |(I - d d^T)(C - C_k)|^2, minimum norm about the mean centre
        proj = np.eye(3)[None] - np.einsum("ki,kj->kij", rays, rays)
        mean = centres.mean(0)
        rhs = np.einsum("kij,kj->i", proj, centres - mean)
        starts = [mean + np.linalg.lstsq(proj.sum(0), rhs, rcond=1e-9)[0]]
        if not np.all(np.einsum("ki,ki->k", starts[0] - centres, rays) > 0):
            ray = np.average(rays, axis=0, weights=weights)
            spread = max(float(np.linalg.norm(centres - mean, axis=1).max()), 1e-3)
            starts = [mean + f * spread * ray / np.linalg.norm(ray) for f in (1, 3, 10, 30)]
    return [np.vstack([np.column_stack([out[:3, :3], c]), out[3]]) for c in starts]


def _landmark_scale(pair: Pair, ray: Array, world_from_query_rot: Array) -> float:
    """Median over the inlier landmarks X of the scale s putting the query centre ``C + s d``
    on its ray r through X, ``s (d x r) = (X - C) x r`` (a 1-D least squares each); 1 m
    without landmarks."""
    use = pair.inliers & pair.has_landmark
    r = pair.q_b[use] @ world_from_query_rot.T
    dxr, rhs = twoview.cross(ray, r), twoview.cross(pair.k_world[use] - pair.keyframe.position_world, r)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (rhs * dxr).sum(1) / (dxr * dxr).sum(1)
    s = s[np.isfinite(s)]
    return float(np.median(s)) if len(s) else 1.0


def _three_point_pose(pairs: list[Pair], gate_px: float, conf: FivePointPoseFinder.Conf
                      ) -> Array | None:
    """``world_from_cam`` by PoseLib P3P LO-RANSAC on the pairs' inlier matches that carry a
    landmark; None without consensus."""
    use = [p.inliers & p.has_landmark for p in pairs]
    ransac = {"max_reproj_error": gate_px, "min_iterations": conf.min_iterations,
              "max_iterations": conf.max_iterations, "success_prob": conf.success_prob,
              "seed": conf.seed}
    pose, info = poselib.estimate_absolute_pose(
        np.concatenate([p.q_px[u] for p, u in zip(pairs, use, strict=True)]),
        np.concatenate([p.k_world[u] for p, u in zip(pairs, use, strict=True)]),
        twoview.ideal(pairs[0].q_cam), ransac, {})
    cam_from_world = np.eye(4)
    cam_from_world[:3, :] = pose.Rt  # PoseLib's pose maps world points into the camera
    return invert(cam_from_world) if info["num_inliers"] >= 4 else None


