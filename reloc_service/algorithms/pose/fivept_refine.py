"""Joint refinement of the five-point pose finder: the query's ``world_from_cam`` by
Gauss-Newton on its right twist (keyframes fixed) over the residual blocks of every
query-keyframe pair at once (landmark reprojections, epipolar errors, a rotation pair's
bounded parallax), its covariance ``(J^T J)^-1``, and each pair's inliers at a pose."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.frame import Keyframe
from ...core.geometry import invert, se3_exp
from . import fivept_twoview as twoview

Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]
#: A residual block: whitened residuals as a function of the query's ``world_from_cam``.
Block = tuple[Callable[[Array], Array], float]

#: sqrt of the 95 % chi-square quantiles (1 and 2 dof): gates, in keypoint sigmas, of the
#: distance to an epipolar plane (1-D) and of a rotation's or a landmark's error (2-D).
GATE_1D, GATE_2D = 1.960, 2.448
_DIFF_STEP = 1e-6    # central differences of the Jacobian, metres and radians


@dataclasses.dataclass
class Pair:
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



def reprojection(world_from_cam: Array, points_h: Array, q_px: Array, q_cam: Camera) -> Array:
    """(2N,) query pixels minus the ideal projections of homogeneous world points (w = 0: a
    direction, which only the rotation moves); 0 where a point is behind the query."""
    cam_from_world = invert(world_from_cam)
    p = points_h[:, :3] @ cam_from_world[:3, :3].T + points_h[:, 3:] * cam_from_world[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.where(p[:, 2:] > 1e-9, p[:, :2] / p[:, 2:], np.nan)
    return np.nan_to_num(q_px - xy * [q_cam.fx, q_cam.fy] - [q_cam.cx, q_cam.cy]).ravel()


def epipolar(world_from_cam: Array, pair: Pair, use: Mask) -> Array:
    """(N,) epipolar errors (px) of the matches ``use`` for the query pose ``world_from_cam``."""
    kf_from_query = invert(pair.keyframe.world_from_cam) @ world_from_cam
    return twoview.epipolar_px(kf_from_query, pair.q_b[use], pair.k_b[use],
                               twoview.focal(pair.keyframe.camera))


def pair_blocks(pair: Pair, mask: Mask, world_from_cam: Array, assumed_m: float | None
                 ) -> list[Block]:
    """Residual blocks of the inliers ``mask`` of a pair.

    Matches with a landmark: its reprojection (which fixes the scale), whitened by the
    landmarks' own RMS at ``world_from_cam`` (triangulation error too), at least the noise.
    General pair: the epipolar errors over the pair's noise.

    Rotation pair: GRIC chose the rotation because the parallax hid in the noise, so the
    query's centre is the keyframe's only up to translations whose image motion, after the
    best compensating rotation, has an RMS below ``eps`` (``fivept._HIDDEN_PARALLAX`` sigma, or the
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
        fun = functools.partial(reprojection, q_px=pair.q_px[lm], q_cam=pair.q_cam,
                                points_h=np.column_stack([pair.k_world[lm], np.ones(lm.sum())]))
        rms = float(np.sqrt(2 * np.mean(fun(world_from_cam) ** 2)))
        blocks.append((fun, 1 / max(pair.sigma_px * np.sqrt(2), rms)))
    if not rest.any():
        return blocks
    if not pair.rotation:
        return [*blocks, (functools.partial(epipolar, pair=pair, use=rest), 1 / pair.sigma_px)]
    dirs = pair.k_b[rest] @ pair.keyframe.world_from_cam[:3, :3].T
    dist = np.linalg.norm(pair.k_world[lm] - pair.keyframe.position_world, axis=1)
    depth = dist.max() if len(dist) else np.inf if assumed_m is None else assumed_m
    points_h = (np.column_stack([pair.keyframe.position_world + depth * dirs, np.ones(len(dirs))])
                if np.isfinite(depth) else np.column_stack([dirs, np.zeros(len(dirs))]))
    fun = functools.partial(reprojection, points_h=points_h, q_px=pair.q_px[rest], q_cam=pair.q_cam)
    return [*blocks, (fun, 1 / (np.sqrt(len(dirs)) * pair.parallax_px))]


def residuals(blocks: list[Block], world_from_cam: Array) -> Array:
    out = [weight * fun(world_from_cam) for fun, weight in blocks]
    return np.concatenate(out) if out else np.zeros(0)


def jacobian(blocks: list[Block], world_from_cam: Array) -> Array:
    """Central-difference Jacobian of the residuals w.r.t. the right twist (rho, omega)."""
    return np.column_stack([
        (residuals(blocks, world_from_cam @ se3_exp(h)) -
         residuals(blocks, world_from_cam @ se3_exp(-h))) / (2 * _DIFF_STEP)
        for h in np.eye(6) * _DIFF_STEP])


def gauss_newton(blocks: list[Block], world_from_cam: Array, iterations: int) -> Array:
    """Gauss-Newton, halving steps that would raise the cost; minimum-norm steps leave an
    unobservable direction alone."""
    residual = residuals(blocks, world_from_cam)
    for _ in range(iterations):
        jac = jacobian(blocks, world_from_cam)
        step = -np.linalg.pinv(jac.T @ jac, rcond=1e-12, hermitian=True) @ (jac.T @ residual)
        for _ in range(6):
            candidate = world_from_cam @ se3_exp(step)
            new = residuals(blocks, candidate)
            if new @ new <= residual @ residual:
                break
            step = step / 2
        else:
            break
        world_from_cam, residual = candidate, new
        if np.linalg.norm(step) < 1e-8:  # 10 nm and 10 nrad: far below any noise
            break
    return world_from_cam


def covariance(blocks: list[Block], world_from_cam: Array) -> Array:
    """``(J^T J)^-1`` of the whitened residuals (6x6, rho then omega, right perturbation);
    infinite when a direction carries no information at all."""
    jac = jacobian(blocks, world_from_cam) if blocks else np.zeros((1, 6))
    info = jac.T @ jac
    eig = np.linalg.eigvalsh(info) if np.all(np.isfinite(info)) else np.zeros(6)
    if eig[-1] <= 0 or eig[0] <= 1e-12 * eig[-1]:
        return np.full((6, 6), np.inf)
    return np.asarray(np.linalg.inv(info), np.float64)


def shared_noise_factor(pairs: list[Pair], masks: tuple[Mask, ...]) -> float:
    """A query keypoint matched in k keyframes enters k two-view residuals with its own
    noise, half of each residual's variance: they correlate by 1/2, and counting them as
    independent overstates the information by the design effect ``1 + (k - 1) / 2``."""
    used = np.concatenate([p.q_raw[m] for p, m in zip(pairs, masks, strict=True)])
    return 1.0 + 0.5 * (len(used) / len(np.unique(used, axis=0)) - 1.0) if len(used) else 1.0


def inliers(pair: Pair, world_from_cam: Array, sigma_px: float) -> tuple[Mask, Array]:
    """Matches within their gate, and the (M,) errors as distances in the joint 4-D image
    space (pixels): the epipolar error (1-D) of a general pair, the transfer error of a
    rotation or the reprojection error of a landmark over sqrt 2 (2-D, noise in both
    images). A general pair seeing the query centre opposite to its own five-point
    translation (points behind a camera) keeps only its landmarks."""
    lm = pair.has_landmark
    err = np.empty(len(lm))
    points_h = np.column_stack([pair.k_world[lm], np.ones(lm.sum())])
    res = reprojection(world_from_cam, points_h, pair.q_px[lm], pair.q_cam).reshape(-1, 2)
    err[lm] = np.linalg.norm(res, axis=1) / np.sqrt(2)
    kf_from_query = invert(pair.keyframe.world_from_cam) @ world_from_cam
    if pair.rotation:
        err[~lm] = twoview.transfer(kf_from_query[:3, :3], pair.q_b[~lm], pair.k_b[~lm],
                             twoview.focal(pair.keyframe.camera)) / np.sqrt(2)
    else:
        err[~lm] = np.abs(epipolar(world_from_cam, pair, ~lm))
    inl = err < np.where(lm | pair.rotation, GATE_2D, GATE_1D) * sigma_px
    if not pair.rotation and kf_from_query[:3, 3] @ pair.kf_from_query[:3, 3] < 0:
        inl &= lm
    return inl, err
