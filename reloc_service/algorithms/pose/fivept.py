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
(keyframes fixed) over all pairs at once (:func:`_pair_blocks`); covariance ``(J^T J)^-1`` of
the whitened residuals: infinite or huge where the position is free (one ray and no landmark,
collinear rays, a rotation and no scene distance), so the shared verification refuses it.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import ClassVar

import numpy as np
import numpy.typing as npt
import poselib

from ...core import features as feature_lib
from ...core.cameras import Camera
from ...core.errors import ConfigError
from ...core.frame import Features, Frame, Keyframe
from ...core.geometry import invert, se3_exp
from ...core.map import MapState
from ..place.base import PlaceCandidate
from .base import PoseEstimate, PoseFinder, log10_false_alarms, register
from .map_uncertainty import keyframes_covariance

Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]
#: A residual block: whitened residuals as a function of the query's ``world_from_cam``.
Block = tuple[Callable[[Array], Array], float]

#: sqrt of the 95 % chi-square quantiles (1 and 2 dof): gates, in keypoint sigmas, of the
#: distance to an epipolar plane (1-D) and of a rotation's or a landmark's error (2-D).
_GATE_1D, _GATE_2D = 1.960, 2.448
#: GRIC (Torr 1998): data dimension r = 4 (two image points), robust cap lambda3 = 2.
_R, _LAMBDA3 = 4, 2.0
#: A rotation fits its data to 2 sigma^2 per point plus half the squared parallax p, the
#: general model to sigma^2 for ln 4 more per point: GRIC keeps the rotation while
#: mean p^2 < 2 (ln 4 - 1) sigma^2. That RMS parallax, in sigmas, hides in the noise.
_HIDDEN_PARALLAX = float(np.sqrt(2 * (np.log(_R) - 1)))
#: Largest expected number of false alarms of a pair's consensus (a-contrario, ORSA): the
#: 1 % wrong-pose budget of the shared verification.
_MAX_FALSE_ALARMS = 1e-2
#: Fewest landmark matches used (the shared verification's floor): below it their residual
#: RMS, which weighs them, is itself unreliable (relative error > 19 %).
_MIN_LANDMARKS = 10
_BATCH = 64          # two-point rotation hypotheses scored at once
_DIFF_STEP = 1e-6    # central differences of the Jacobian, metres and radians


@dataclasses.dataclass
class _Pair:
    """One query-keyframe pair: its M matches and the chosen model."""

    keyframe: Keyframe
    q_cam: Camera
    q_raw: Array           # (M, 2) query pixels as detected
    q_px: Array            # (M, 2) ideal pinhole pixels of the query
    q_b: Array             # (M, 3) unit bearings, query and keyframe
    k_b: Array
    k_world: Array         # (M, 3) the keyframe keypoints' landmarks (NaN: none)
    kf_from_query: Array   # (4, 4): unit translation, or none for a rotation pair
    rotation: bool
    inliers: Mask
    sigma_px: float        # keypoint noise, from the general model's inliers
    chance: float          # probability that a random match falls within the gate
    parallax_px: float     # RMS parallax a rotation pair allows (at least the hidden one)

    @property
    def has_landmark(self) -> Mask:
        return np.asarray(np.isfinite(self.k_world).all(1), dtype=bool)


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
        pairs: list[_Pair] = []
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
                  k_world: Array) -> _Pair | None:
        """Both models by RANSAC and GRIC's choice; None if chance could explain it."""
        c, k_cam = self.conf, kf.camera
        q_px, k_px = q_cam.undistort_pixels(q_raw), k_cam.undistort_pixels(k_raw)
        ok = np.isfinite(q_px).all(1) & np.isfinite(k_px).all(1)
        n, f = int(ok.sum()), _focal(k_cam)
        if n < 6:  # a five-point sample and one match to check it
            return None
        q_b, k_b = _bearings(q_cam, q_px[ok]), _bearings(k_cam, k_px[ok])
        ransac = {"max_epipolar_error": _GATE_1D * c.keypoint_sigma_px, "seed": c.seed,
                  "min_iterations": c.min_iterations, "max_iterations": c.max_iterations,
                  "success_prob": c.success_prob}
        pose, info = poselib.estimate_relative_pose(q_px[ok], k_px[ok], _ideal(q_cam),
                                                    _ideal(k_cam), ransac, {})
        general = np.eye(4)
        general[:3, :] = pose.Rt  # PoseLib's pose maps query points into the keyframe
        e_inl = np.asarray(info["inliers"], bool)
        rot = _rotation_ransac(q_b, k_b, f, _GATE_2D * np.sqrt(2) * c.keypoint_sigma_px,
                               e_inl.mean(), c)
        e_gen = _epipolar_px(general, q_b, k_b, f)
        e_rot = _transfer(rot, q_b, k_b, f) / np.sqrt(2)  # as a distance in 4-D
        # Noise from the general model's inliers (the median of |N(0, s^2)| is 0.674 s).
        sigma = max(c.min_sigma_px, 1.4826 * float(np.median(np.abs(e_gen[e_inl])))
                    if e_inl.any() else c.keypoint_sigma_px)
        rotation = _gric(e_rot, sigma, 2, 3) < _gric(e_gen, sigma, 3, 5)
        gate = (_GATE_2D if rotation else _GATE_1D) * c.keypoint_sigma_px
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
        return _Pair(kf, q_cam, q_raw[ok], q_px[ok], q_b, k_b, k_world[ok], kf_from_query,
                     bool(rotation), inliers, sigma, p,
                     max(float(parallax), _HIDDEN_PARALLAX * sigma))

    def _refine(self, pairs: list[_Pair], pose: Array, masks: tuple[Mask, ...] | None = None
                ) -> tuple[float, Array, tuple[Mask, ...], tuple[Array, ...]]:
        """Joint Gauss-Newton from ``pose``, inliers re-selected after it: (MSAC score, pose,
        inlier masks and errors per pair)."""
        sigma = self.conf.keypoint_sigma_px
        if masks is None:  # landmarks may be badly triangulated: those fitting ``pose`` only
            masks = tuple(p.inliers & (_inliers(p, pose, sigma)[0] | ~p.has_landmark)
                          for p in pairs)
        blocks = [b for p, m in zip(pairs, masks, strict=True)
                  for b in _pair_blocks(p, m, pose, self.conf.assumed_depth_m)]
        pose = _gauss_newton(blocks, pose, self.conf.refine_iterations)
        masks, errs = zip(*(_inliers(p, pose, sigma) for p in pairs), strict=True)
        gates = [np.where(p.has_landmark | p.rotation, _GATE_2D, _GATE_1D) * sigma for p in pairs]
        capped = [np.minimum(e, g) for e, g in zip(errs, gates, strict=True)]
        return sum(float(e @ e) for e in capped), pose, masks, errs

    def _solve(self, pairs: list[_Pair], state: MapState) -> PoseEstimate:
        """The best hypothesis refined (MSAC score), its covariance and evidence; the pose
        rests on the keyframes' poses (their rays), each by its share of the inliers, so
        their covariances move to it (:func:`.map_uncertainty.keyframes_covariance`)."""
        c = self.conf
        # Landmarks carry triangulation errors, not keypoint noise: they take part only
        # where the rays leave the scale free, and only enough of them. Then the three-point
        # pose (thesis: "if depth is known") is a hypothesis too: it also settles the
        # two-fold five-point ambiguity of a plane.
        landmarks = sum(int((p.inliers & p.has_landmark).sum()) for p in pairs)
        landmark_pose = (_three_point_pose(pairs, _GATE_2D * np.sqrt(2) * c.keypoint_sigma_px, c)
                         if landmarks >= _MIN_LANDMARKS else None)
        if sum(not p.rotation for p in pairs) >= 2 or landmarks < _MIN_LANDMARKS:
            pairs = [dataclasses.replace(p, k_world=np.full_like(p.k_world, np.nan)) for p in pairs]
        inits = _initial_poses(pairs) + ([] if landmark_pose is None else [landmark_pose])
        _, pose, masks, _ = min((self._refine(pairs, init) for init in inits), key=lambda r: r[0])
        _, pose, masks, errs = self._refine(pairs, pose, masks)  # the winner, once more
        blocks = [b for p, m in zip(pairs, masks, strict=True)
                  for b in _pair_blocks(p, m, pose, c.assumed_depth_m)]
        errors = np.concatenate([e[m] for e, m in zip(errs, masks, strict=True)])
        counts = np.array([m.sum() for m in masks])
        order = np.argsort(counts, kind="stable")[::-1]
        return PoseEstimate(
            world_from_cam=pose, keyframe_ids=[pairs[i].keyframe.id for i in order if counts[i]],
            inliers=len(errors),
            reprojection_rms_px=float(np.sqrt(np.mean(errors**2))) if len(errors) else None,
            covariance=_covariance(blocks, pose) * _shared_noise_factor(pairs, masks),
            map_covariance=keyframes_covariance(pose, state, [p.keyframe.id for p in pairs],
                                                counts),
            inlier_px=np.concatenate([p.q_raw[m] for p, m in zip(pairs, masks, strict=True)]),
            image_size=pairs[0].q_cam.size,
            # For the a-contrario test: the gate, every pair's minimal sample (the joint pose
            # rests on all of them), the chance agreement of a match (bands, discs).
            inlier_threshold_px=(_GATE_2D if all(p.rotation for p in pairs) else _GATE_1D)
            * c.keypoint_sigma_px,
            sample_size=sum(2 if p.rotation else 5 for p, k in zip(pairs, counts, strict=True) if k),
            chance_probability=float(np.average([p.chance for p in pairs], weights=counts + 1e-9)))


# -- two-view geometry -------------------------------------------------------------------------
def _ideal(camera: Camera) -> dict[str, object]:
    """The ideal pinhole camera with ``camera``'s K, for PoseLib."""
    return {"model": "PINHOLE", "width": camera.width, "height": camera.height,
            "params": [camera.fx, camera.fy, camera.cx, camera.cy]}


def _bearings(camera: Camera, ideal_px: Array) -> Array:
    """(N, 3) unit bearings of ideal pinhole pixels."""
    b = np.column_stack([(ideal_px - [camera.cx, camera.cy]) / [camera.fx, camera.fy],
                         np.ones(len(ideal_px))])
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _focal(camera: Camera) -> float:
    return float(np.sqrt(camera.fx * camera.fy))


def _kabsch(a: Array, b: Array) -> Array:
    """(..., 3, 3) rotations R minimising sum |b_i - R a_i|^2 over (..., n, 3) bearings."""
    u, _, vt = np.linalg.svd(np.einsum("...ni,...nj->...ij", b, a))
    u[..., :, 2] *= np.sign(np.linalg.det(u @ vt))[..., None]
    return u @ vt


def _rotation_ransac(q_b: Array, k_b: Array, focal_px: float, gate_px: float,
                     essential_ratio: float, conf: FivePointPoseFinder.Conf) -> Array:
    """Rotation ``kf_from_query`` of a pure rotation (``k_b ~ R q_b``): two-point Kabsch
    hypotheses in batches scored by their transfer errors, then three least-squares refits on
    the inliers (LO-RANSAC). A rotation's inliers are inliers of the essential matrix too, so
    samples enough to draw two of those (``essential_ratio``) with ``success_prob`` suffice:
    a rotation needing more would lose the model selection anyway."""
    rng = np.random.default_rng(conf.seed)
    n, best, best_count, tried = len(q_b), np.eye(3), -1, 0
    miss = max(1 - essential_ratio**2, 1e-12)  # P(a sample is not two inliers)
    needed = conf.min_iterations if miss >= 1 else max(
        conf.min_iterations, np.log(1 - conf.success_prob) / np.log(miss))
    while tried < min(needed, conf.max_iterations):
        idx = rng.integers(0, n, (_BATCH, 2))
        rots = _kabsch(q_b[idx], k_b[idx])
        err = np.linalg.norm(np.einsum("hij,nj->hni", rots, q_b) - k_b, axis=2) * focal_px
        counts = (err < gate_px).sum(1)
        if counts.max() > best_count:
            best, best_count = rots[counts.argmax()], int(counts.max())
        tried += _BATCH
    for _ in range(3):
        inl = _transfer(best, q_b, k_b, focal_px) < gate_px
        if inl.sum() >= 2:
            best = _kabsch(q_b[inl], k_b[inl])
    return best


def _transfer(kf_from_query_rot: Array, q_b: Array, k_b: Array, focal_px: float) -> Array:
    """(N,) transfer errors of a rotation: the angle (chord) between the keyframe bearings
    and the turned query bearings, times f; angles like the epipolar error, so that GRIC
    compares the two models in the same units."""
    return np.linalg.norm(q_b @ kf_from_query_rot.T - k_b, axis=1) * focal_px


def _epipolar_px(kf_from_query: Array, q_b: Array, k_b: Array, focal_px: float) -> Array:
    """(N,) signed angle of each pair of bearings to their best epipolar plane (through the
    baseline t and their mean direction), ``[t, R q_b, k_b] / |t x (k_b + R q_b)|``, times
    ``sqrt 2 f``: keypoint noise sigma gives errors of about sigma, like the Sampson
    distance, which instead blows up near the epipole (forward motion, tiny baselines)."""
    t, r_qb = kf_from_query[:3, 3], q_b @ kf_from_query[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        angle = (k_b * _cross(t, r_qb)).sum(1) / np.linalg.norm(_cross(t, k_b + r_qb), axis=1)
    return np.where(np.isfinite(angle), angle, 0.0) * np.sqrt(2) * focal_px


def _cross(a: Array, b: Array) -> Array:
    """Cross products of (3,) or (N, 3) vectors (np.cross's overhead dominates in the loop)."""
    a, b = np.broadcast_arrays(a, b)
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _gric(errors_px: Array, sigma_px: float, d: int, k: int) -> float:
    """Torr's GRIC of a model of dimension ``d`` with ``k`` parameters (lower is better)."""
    n = len(errors_px)
    robust = np.minimum((errors_px / sigma_px) ** 2, _LAMBDA3 * (_R - d)).sum()
    return float(robust + np.log(_R) * d * n + np.log(_R * n) * k)


# -- the query's pose --------------------------------------------------------------------------
def _initial_poses(pairs: list[_Pair]) -> list[Array]:
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


def _landmark_scale(pair: _Pair, ray: Array, world_from_query_rot: Array) -> float:
    """Median over the inlier landmarks X of the scale s putting the query centre ``C + s d``
    on its ray r through X, ``s (d x r) = (X - C) x r`` (a 1-D least squares each); 1 m
    without landmarks."""
    use = pair.inliers & pair.has_landmark
    r = pair.q_b[use] @ world_from_query_rot.T
    dxr, rhs = _cross(ray, r), _cross(pair.k_world[use] - pair.keyframe.position_world, r)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (rhs * dxr).sum(1) / (dxr * dxr).sum(1)
    s = s[np.isfinite(s)]
    return float(np.median(s)) if len(s) else 1.0


def _three_point_pose(pairs: list[_Pair], gate_px: float, conf: FivePointPoseFinder.Conf
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
        _ideal(pairs[0].q_cam), ransac, {})
    cam_from_world = np.eye(4)
    cam_from_world[:3, :] = pose.Rt  # PoseLib's pose maps world points into the camera
    return invert(cam_from_world) if info["num_inliers"] >= 4 else None


def _reprojection(world_from_cam: Array, points_h: Array, q_px: Array, q_cam: Camera) -> Array:
    """(2N,) query pixels minus the ideal projections of homogeneous world points (w = 0: a
    direction, which only the rotation moves); 0 where a point is behind the query."""
    cam_from_world = invert(world_from_cam)
    p = points_h[:, :3] @ cam_from_world[:3, :3].T + points_h[:, 3:] * cam_from_world[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.where(p[:, 2:] > 1e-9, p[:, :2] / p[:, 2:], np.nan)
    return np.nan_to_num(q_px - xy * [q_cam.fx, q_cam.fy] - [q_cam.cx, q_cam.cy]).ravel()


def _epipolar(world_from_cam: Array, pair: _Pair, use: Mask) -> Array:
    """(N,) epipolar errors (px) of the matches ``use`` for the query pose ``world_from_cam``."""
    kf_from_query = invert(pair.keyframe.world_from_cam) @ world_from_cam
    return _epipolar_px(kf_from_query, pair.q_b[use], pair.k_b[use], _focal(pair.keyframe.camera))


def _pair_blocks(pair: _Pair, mask: Mask, world_from_cam: Array, assumed_m: float | None
                 ) -> list[Block]:
    """Residual blocks of the inliers ``mask`` of a pair.

    Matches with a landmark: its reprojection (which fixes the scale), whitened by the
    landmarks' own RMS at ``world_from_cam`` (triangulation error too), at least the noise.
    General pair: the epipolar errors over the pair's noise.

    Rotation pair: GRIC chose the rotation because the parallax hid in the noise, so the
    query's centre is the keyframe's only up to translations whose image motion, after the
    best compensating rotation, has an RMS below ``eps`` (``_HIDDEN_PARALLAX sigma``, or the
    inliers' residual parallax if larger). With the scene at distance Z, the
    keyframe bearings at Z are pseudo-points whitened by ``sqrt(n) eps``: their information
    ``J^T J / (n eps^2)`` is exactly that ellipsoid of poses, about ``Z eps / f`` sideways,
    more along the axis and where a rotation mimics a translation. Z is the farthest inlier
    landmark, else ``assumed_m`` (an upper bound, so the ellipsoid is too); with neither the
    bearings are directions at infinity: the rotation is bounded, the position not at all."""
    lm = mask & pair.has_landmark
    rest = mask & ~lm
    blocks: list[Block] = []
    if lm.any():
        fun = functools.partial(_reprojection, q_px=pair.q_px[lm], q_cam=pair.q_cam,
                                points_h=np.column_stack([pair.k_world[lm], np.ones(lm.sum())]))
        rms = float(np.sqrt(2 * np.mean(fun(world_from_cam) ** 2)))
        blocks.append((fun, 1 / max(pair.sigma_px * np.sqrt(2), rms)))
    if not rest.any():
        return blocks
    if not pair.rotation:
        return [*blocks, (functools.partial(_epipolar, pair=pair, use=rest), 1 / pair.sigma_px)]
    dirs = pair.k_b[rest] @ pair.keyframe.world_from_cam[:3, :3].T
    dist = np.linalg.norm(pair.k_world[lm] - pair.keyframe.position_world, axis=1)
    depth = dist.max() if len(dist) else np.inf if assumed_m is None else assumed_m
    points_h = (np.column_stack([pair.keyframe.position_world + depth * dirs, np.ones(len(dirs))])
                if np.isfinite(depth) else np.column_stack([dirs, np.zeros(len(dirs))]))
    fun = functools.partial(_reprojection, points_h=points_h, q_px=pair.q_px[rest], q_cam=pair.q_cam)
    return [*blocks, (fun, 1 / (np.sqrt(len(dirs)) * pair.parallax_px))]


def _residuals(blocks: list[Block], world_from_cam: Array) -> Array:
    out = [weight * fun(world_from_cam) for fun, weight in blocks]
    return np.concatenate(out) if out else np.zeros(0)


def _jacobian(blocks: list[Block], world_from_cam: Array) -> Array:
    """Central-difference Jacobian of the residuals w.r.t. the right twist (rho, omega)."""
    return np.column_stack([
        (_residuals(blocks, world_from_cam @ se3_exp(h)) -
         _residuals(blocks, world_from_cam @ se3_exp(-h))) / (2 * _DIFF_STEP)
        for h in np.eye(6) * _DIFF_STEP])


def _gauss_newton(blocks: list[Block], world_from_cam: Array, iterations: int) -> Array:
    """Gauss-Newton, halving steps that would raise the cost; minimum-norm steps leave an
    unobservable direction alone."""
    residual = _residuals(blocks, world_from_cam)
    for _ in range(iterations):
        jac = _jacobian(blocks, world_from_cam)
        step = -np.linalg.pinv(jac.T @ jac, rcond=1e-12, hermitian=True) @ (jac.T @ residual)
        for _ in range(6):
            candidate = world_from_cam @ se3_exp(step)
            new = _residuals(blocks, candidate)
            if new @ new <= residual @ residual:
                break
            step = step / 2
        else:
            break
        world_from_cam, residual = candidate, new
        if np.linalg.norm(step) < 1e-8:  # 10 nm and 10 nrad: far below any noise
            break
    return world_from_cam


def _covariance(blocks: list[Block], world_from_cam: Array) -> Array:
    """``(J^T J)^-1`` of the whitened residuals (6x6, rho then omega, right perturbation);
    infinite when a direction carries no information at all."""
    jac = _jacobian(blocks, world_from_cam) if blocks else np.zeros((1, 6))
    info = jac.T @ jac
    eig = np.linalg.eigvalsh(info) if np.all(np.isfinite(info)) else np.zeros(6)
    if eig[-1] <= 0 or eig[0] <= 1e-12 * eig[-1]:
        return np.full((6, 6), np.inf)
    return np.asarray(np.linalg.inv(info), np.float64)


def _shared_noise_factor(pairs: list[_Pair], masks: tuple[Mask, ...]) -> float:
    """A query keypoint matched in k keyframes enters k two-view residuals with its own
    noise, half of each residual's variance: they correlate by 1/2, and counting them as
    independent overstates the information by the design effect ``1 + (k - 1) / 2``."""
    used = np.concatenate([p.q_raw[m] for p, m in zip(pairs, masks, strict=True)])
    return 1.0 + 0.5 * (len(used) / len(np.unique(used, axis=0)) - 1.0) if len(used) else 1.0


def _inliers(pair: _Pair, world_from_cam: Array, sigma_px: float) -> tuple[Mask, Array]:
    """Matches within their gate, and the (M,) errors as distances in the joint 4-D image
    space (pixels): the epipolar error (1-D) of a general pair, the transfer error of a
    rotation or the reprojection error of a landmark over sqrt 2 (2-D, noise in both
    images). A general pair seeing the query centre opposite to its own five-point
    translation (points behind a camera) keeps only its landmarks."""
    lm = pair.has_landmark
    err = np.empty(len(lm))
    points_h = np.column_stack([pair.k_world[lm], np.ones(lm.sum())])
    res = _reprojection(world_from_cam, points_h, pair.q_px[lm], pair.q_cam).reshape(-1, 2)
    err[lm] = np.linalg.norm(res, axis=1) / np.sqrt(2)
    kf_from_query = invert(pair.keyframe.world_from_cam) @ world_from_cam
    if pair.rotation:
        err[~lm] = _transfer(kf_from_query[:3, :3], pair.q_b[~lm], pair.k_b[~lm],
                             _focal(pair.keyframe.camera)) / np.sqrt(2)
    else:
        err[~lm] = np.abs(_epipolar(world_from_cam, pair, ~lm))
    inl = err < np.where(lm | pair.rotation, _GATE_2D, _GATE_1D) * sigma_px
    if not pair.rotation and kf_from_query[:3, 3] @ pair.kf_from_query[:3, 3] < 0:
        inl &= lm
    return inl, err
