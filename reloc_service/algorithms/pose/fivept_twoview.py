"""Two-view geometry of the five-point pose finder: bearings of ideal pinhole pixels, a pure
rotation by two-point Kabsch LO-RANSAC, its transfer error, the epipolar error as an angle
in pixels, and Torr's GRIC to choose between the rotation and the general model."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera

Array = npt.NDArray[np.float64]


class RansacConf(Protocol):
    """The RANSAC settings the rotation search reads (the five-point finder's ``Conf``)."""

    @property
    def min_iterations(self) -> int: ...
    @property
    def max_iterations(self) -> int: ...
    @property
    def success_prob(self) -> float: ...
    @property
    def seed(self) -> int: ...

#: GRIC (Torr 1998): data dimension r = 4 (two image points), robust cap lambda3 = 2.
GRIC_R, _LAMBDA3 = 4, 2.0
_BATCH = 64          # two-point rotation hypotheses scored at once


def ideal(camera: Camera) -> dict[str, object]:
    """The ideal pinhole camera with ``camera``'s K, for PoseLib."""
    return {"model": "PINHOLE", "width": camera.width, "height": camera.height,
            "params": [camera.fx, camera.fy, camera.cx, camera.cy]}


def bearings(camera: Camera, ideal_px: Array) -> Array:
    """(N, 3) unit bearings of ideal pinhole pixels."""
    b = np.column_stack([(ideal_px - [camera.cx, camera.cy]) / [camera.fx, camera.fy],
                         np.ones(len(ideal_px))])
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def focal(camera: Camera) -> float:
    return float(np.sqrt(camera.fx * camera.fy))


def kabsch(a: Array, b: Array) -> Array:
    """(..., 3, 3) rotations R minimising sum |b_i - R a_i|^2 over (..., n, 3) bearings."""
    u, _, vt = np.linalg.svd(np.einsum("...ni,...nj->...ij", b, a))
    u[..., :, 2] *= np.sign(np.linalg.det(u @ vt))[..., None]
    return u @ vt


def rotation_ransac(q_b: Array, k_b: Array, focal_px: float, gate_px: float,
                     essential_ratio: float, conf: RansacConf) -> Array:
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
        rots = kabsch(q_b[idx], k_b[idx])
        err = np.linalg.norm(np.einsum("hij,nj->hni", rots, q_b) - k_b, axis=2) * focal_px
        counts = (err < gate_px).sum(1)
        if counts.max() > best_count:
            best, best_count = rots[counts.argmax()], int(counts.max())
        tried += _BATCH
    for _ in range(3):
        inl = transfer(best, q_b, k_b, focal_px) < gate_px
        if inl.sum() >= 2:
            best = kabsch(q_b[inl], k_b[inl])
    return best


def transfer(kf_from_query_rot: Array, q_b: Array, k_b: Array, focal_px: float) -> Array:
    """(N,) transfer errors of a rotation: the angle (chord) between the keyframe bearings
    and the turned query bearings, times f; angles like the epipolar error, so that GRIC
    compares the two models in the same units."""
    return np.linalg.norm(q_b @ kf_from_query_rot.T - k_b, axis=1) * focal_px


def epipolar_px(kf_from_query: Array, q_b: Array, k_b: Array, focal_px: float) -> Array:
    """(N,) signed angle of each pair of bearings to their best epipolar plane (through the
    baseline t and their mean direction), ``[t, R q_b, k_b] / |t x (k_b + R q_b)|``, times
    ``sqrt 2 f``: keypoint noise sigma gives errors of about sigma, like the Sampson
    distance, which instead blows up near the epipole (forward motion, tiny baselines)."""
    t, r_qb = kf_from_query[:3, 3], q_b @ kf_from_query[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        angle = (k_b * cross(t, r_qb)).sum(1) / np.linalg.norm(cross(t, k_b + r_qb), axis=1)
    return np.where(np.isfinite(angle), angle, 0.0) * np.sqrt(2) * focal_px


def cross(a: Array, b: Array) -> Array:
    """Cross products of (3,) or (N, 3) vectors (np.cross's overhead dominates in the loop)."""
    a, b = np.broadcast_arrays(a, b)
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def gric(errors_px: Array, sigma_px: float, d: int, k: int) -> float:
    """Torr's GRIC of a model of dimension ``d`` with ``k`` parameters (lower is better)."""
    n = len(errors_px)
    robust = np.minimum((errors_px / sigma_px) ** 2, _LAMBDA3 * (GRIC_R - d)).sum()
    return float(robust + np.log(GRIC_R) * d * n + np.log(GRIC_R * n) * k)
