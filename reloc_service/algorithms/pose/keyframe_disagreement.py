"""The keyframes' pose uncertainty a map shows itself: each keyframe's pose re-estimated on
its landmarks re-triangulated without it, and how much more those re-estimates disagree with
the poses put than their own noise explains.

A keyframe pose off by a few centimetres or tenths of a degree (a motion-capture or
KinectFusion ground truth, a visual-inertial odometry) places its landmarks off by as much,
and a query's pose solved on them inherits it (:mod:`.map_uncertainty`). Where the keyframes
are put without a covariance, the map measures it: held out of its landmarks (each
re-triangulated from its other observations, :func:`.held_out.held_out_points`), a
keyframe's pose solved on them by Gauss-Newton from the pose put moves by ``d`` (twist
(rho, omega), right perturbation), whose covariance is the pose's own error relative to the
rest of the map, ``S``, plus the solve's a-posteriori covariance ``C`` (its residuals' scale
times the inverse normal matrix: keypoint and held-out landmark noise). Per axis, ``S``'s
variance is the mean square of ``d``'s components beyond ``C``'s, estimated robustly over the
keyframes (the median of ``|d|^2`` over the median of chi-square with 3 degrees of freedom,
so a keyframe with mis-associated landmarks does not set it) for the position and the
rotation apart; a bootstrap over the keyframes gives its sampling uncertainty.

What is measured is each keyframe's error relative to the others that fix its held-out
landmarks: an error all keyframes share (a ground-truth system's calibration) is invisible
to the map, and to a query whose ground truth comes from the same system alike. A map of
exact poses (a rendered dataset) measures about zero (the synthetic dev sets: 0.0-0.04 cm and
0.01-0.02 deg, the residue of a-posteriori covariances a little narrower than the re-solves'
spread). Weaknesses: an error that differs between the map's pass and a query's (KinectFusion
drift between passes of 7-Scenes, TUM's per-frame motion-capture jitter at fast rotation) is
invisible to it, so such maps measure less than their ground truth's stated accuracy (tum
0.4 cm and 0.22 deg, 7-Scenes 0.4 cm and 0.13 deg, against the README's 1-3 cm and
0.3-0.7 deg); and a calibration error makes keyframes disagree as well, which the answer's
calibration covariance (:mod:`.intrinsics_marginal`) then counts a second time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core import distributions as stats
from ...core.cameras import Camera
from ...core.geometry import invert, pose_covariance_from_sigmas, se3_exp, se3_log
from ...core.map import MapState
from ...core.triangulation import keypoint_sigmas
from .held_out import held_out_candidates, held_out_points
from .map_consistency import MIN_HELD_OUT
from .pnp import solve_pnp_indexed
from .pnp_conf import PnPConf
from .projection import pose_projector

Array = npt.NDArray[np.float64]

#: Keyframes re-estimated at most (evenly spread over the map's ids): enough for a median
#: good to a few per cent, at a fraction of a second per keyframe.
MAX_KEYFRAMES = 80
#: Keyframes that must give a re-estimate for the map to state a measurement.
MIN_KEYFRAMES = 5
#: Gauss-Newton steps on a re-estimate's inliers (it starts at the refined RANSAC pose).
STEPS = 3
#: Bootstrap resamples over the keyframes, and the two-sided coverage of the interval they give.
BOOTSTRAP = 200
INTERVAL = 0.68

#: Medians of chi-square with 3 degrees of freedom: ``|d|^2`` of an isotropic 3-vector.
CHI2_3_MEDIAN = float(stats.chi2.median(3))


@dataclass(frozen=True)
class KeyframePoseSigma:
    """A map's measured keyframe pose uncertainty, 1 sigma per axis: position (metres) and
    rotation (degrees), each with the bounds of its ``INTERVAL`` bootstrap interval, and the
    number of keyframes it rests on."""

    position_m: float
    rotation_deg: float
    position_interval_m: tuple[float, float]
    rotation_interval_deg: tuple[float, float]
    keyframes: int

    def covariance(self) -> Array:
        """(6, 6) the pose covariance it states (twist (rho, omega), independent axes)."""
        return pose_covariance_from_sigmas(self.position_m, np.radians(self.rotation_deg))

    def as_dict(self) -> dict[str, float]:
        """Flat numbers, what a status and an evaluation's map info report: ``position_m``,
        ``rotation_deg``, their interval bounds (``position_low_m``, ``position_high_m``,
        ``rotation_low_deg``, ``rotation_high_deg``) and ``keyframes``."""
        return {"position_m": self.position_m, "position_low_m": self.position_interval_m[0],
                "position_high_m": self.position_interval_m[1],
                "rotation_deg": self.rotation_deg, "rotation_low_deg": self.rotation_interval_deg[0],
                "rotation_high_deg": self.rotation_interval_deg[1],
                "keyframes": float(self.keyframes)}


def keyframe_pose_sigma(state: MapState, *, max_keyframes: int = MAX_KEYFRAMES,
                        seed: int = 0) -> KeyframePoseSigma | None:
    """The keyframe pose uncertainty ``state`` shows (module docstring); None where fewer
    than :data:`MIN_KEYFRAMES` keyframes have :data:`MIN_HELD_OUT` held-out landmarks."""
    kind = _main_kind(state)
    if kind is None:
        return None
    ids = state.keyframe_ids()
    pick = np.unique(np.linspace(0, len(ids) - 1, min(len(ids), max_keyframes)).astype(np.int64))
    fits = [fit for i in pick.tolist() if (fit := disagreement(state, ids[i], kind)) is not None]
    if len(fits) < MIN_KEYFRAMES:
        return None
    moved = np.array([f[0] for f in fits])             # (K, 6) d
    noise = np.array([np.diag(f[1]) for f in fits])    # (K, 6) diag C
    position = _excess_sigmas(moved[:, :3], noise[:, :3], seed)
    rotation = np.degrees(_excess_sigmas(moved[:, 3:], noise[:, 3:], seed + 1))
    return KeyframePoseSigma(float(position[0]), float(rotation[0]),
                             (float(position[1]), float(position[2])),
                             (float(rotation[1]), float(rotation[2])), len(fits))


def _excess_sigmas(moved: Array, noise: Array, seed: int) -> Array:
    """(3,) the per-axis sigma beyond the noise (:func:`_excess_sigma`) of the (K, 3)
    ``moved`` with (K, 3) noise variances, and its bootstrap interval's bounds."""
    point = _excess_sigma(moved, noise)
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(moved), size=(BOOTSTRAP, len(moved)))
    spread = np.array([_excess_sigma(moved[d], noise[d]) for d in draws])
    tail = (1.0 - INTERVAL) / 2.0
    return np.array([point, *np.quantile(spread, [tail, 1.0 - tail])])


def _excess_sigma(moved: Array, noise: Array) -> float:
    """Per-axis sigma of (K, 3) isotropic displacements beyond their (K, 3) noise variances:
    the robust total variance (median of ``|d|^2`` over chi-square 3's) less the median noise
    variance, at least 0."""
    total = float(np.median(np.sum(moved**2, axis=1))) / CHI2_3_MEDIAN
    return float(np.sqrt(max(total - float(np.median(noise.mean(axis=1))), 0.0)))


def _main_kind(state: MapState) -> str | None:
    """The feature kind with the most landmark observations (None: no landmarks)."""
    cols = state.landmarks.columns()
    if len(cols) == 0 or not cols.kinds:
        return None
    return cols.kinds[int(np.argmax(np.bincount(cols.obs_kind, minlength=len(cols.kinds))))]


def disagreement(state: MapState, kf_id: int, kind: str) -> tuple[Array, Array] | None:
    """Keyframe ``kf_id``'s pose re-estimated on its ``kind`` landmarks held out of it: the
    (6,) twist ``d`` from the pose put to the re-estimate and the (6, 6) a-posteriori
    covariance of the re-estimate; None with fewer than :data:`MIN_HELD_OUT` landmarks."""
    keyframe = state.keyframes[kf_id]
    feats = keyframe.features.get(kind)
    if feats is None:
        return None
    cols = state.landmarks.columns()
    observed, rows = held_out_candidates(cols, feats.landmark_ids)
    points, held = held_out_points(state, cols, rows, kf_id, kind)
    if held.sum() < MIN_HELD_OUT:
        return None
    px = feats.keypoints_px[observed[held]].astype(np.float64)
    sigmas = keypoint_sigmas(feats)[observed[held]]
    return _solve(keyframe.world_from_cam, px, sigmas, points[held], keyframe.camera)


def _solve(world_from_cam: Array, px: Array, sigmas: Array, points_world: Array,
           camera: Camera) -> tuple[Array, Array] | None:
    """The pose of (N, 2) ``px`` on (N, 3) ``points_world`` solved as a query's is (RANSAC
    from scratch, so that how far ``world_from_cam`` is off does not decide which residuals
    count, then refined on its inliers), and Gauss-Newton on the inliers to convergence:
    (6,) the twist from ``world_from_cam`` to it and (6, 6) its a-posteriori covariance (the
    residuals' scale, weighted by their keypoints' relative ``sigmas`` (N,), times the
    inverse normal matrix)."""
    solved = solve_pnp_indexed(px, points_world, camera, PnPConf(), keypoint_scales=sigmas)
    if solved is None or len(solved[1]) < MIN_HELD_OUT:
        return None
    rows = solved[1]
    project = pose_projector(points_world[rows], camera)
    px, w = px[rows], np.repeat(1.0 / sigmas[rows] ** 2, 2)
    pose = solved[0].world_from_cam
    for _ in range(STEPS):
        predicted, jac = project(pose)
        jac = jac.reshape(-1, 6)
        step = np.linalg.solve(jac.T @ (w[:, None] * jac), jac.T @ (w * (px - predicted).ravel()))
        pose = pose @ se3_exp(step)
    predicted, jac = project(pose)
    jac = jac.reshape(-1, 6)
    residual = (px - predicted).ravel()
    scale = float(w @ residual**2) / max(len(residual) - 6, 1)
    covariance = np.asarray(scale * np.linalg.inv(jac.T @ (w[:, None] * jac)), np.float64)
    return se3_log(invert(world_from_cam) @ pose), covariance
