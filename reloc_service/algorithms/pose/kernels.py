"""Compiled projection and pose Jacobian (numba, the optional ``[jit]`` extra) for the pinhole
and radtan cameras, bit for bit the numpy path's values; the refinement's fused pass
(:func:`_fit`), Gauss-Newton update and covariance inverse, its values to rounding.
(Guided matching's window test has its own: :mod:`.guided_kernels`; the repetition index's
leaf scan too: :mod:`.repetition_kernels`.)

The P3P refinement projects a few hundred points and differentiates their pixels several
times per query; in numpy each of those is some forty array operations of a few microseconds
each on arrays of a few hundred values, so the calls, not the arithmetic, cost the time. Here
each point's values come from one loop iteration. Every expression below is the numpy path's
(:meth:`~reloc_service.core.cameras.Camera.project`, :meth:`RadTanCamera.distort
<reloc_service.core.cameras.RadTanCamera.distort>`, ``RadTanCamera._jacobian``,
:func:`~reloc_service.algorithms.pose.projection.pose_jacobian`) with its operations in the same order (Python
evaluates ``2 * p1 * x * y`` as ``((2 * p1) * x) * y``, and so does numba; numba contracts no
multiply-add into an FMA without ``fastmath``), so the results are the same to the bit:
``tests/test_pose_kernels.py`` compares both paths on the points of real queries.

:func:`_fit` goes further: one pass over the correspondences of a pose gives its inliers and
their weighted normal equations, with no (2N, 6) Jacobian in between; one call each solves
them and applies the step (:func:`_gauss_newton_update`) and inverts them for the covariance
(:func:`_spd_inverse`). Their sums run in point order and the 6x6 algebra is Cholesky, where
the numpy path has BLAS products and LAPACK's LU, so they agree to rounding (about 1e-16 in
the pose), not to the bit; the inliers and verdicts are the same (the tests check both). In a
cold cache (the bench's interleaved methods) these three save about 0.37 ms of a desk query's
1.6 ms solve: numba's and NumPy's per-call costs, not arithmetic.

:func:`compiled` imports numba on first use and returns None where it is not installed (the
numpy path then runs).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from ...core.numeric import compile_once, numba_or_none
from . import guided_kernels, intrinsics_kernels, keypoint_grid, repetition_kernels

Array = npt.NDArray[np.float64]


def _distort(x: float, y: float, params: Array, distorted: bool) -> tuple[float, float]:
    """``RadTanCamera.distort`` of one normalised point (``params`` fx fy cx cy k1 k2 p1 p2
    k3); the point itself for a pinhole camera (``distorted`` False)."""
    if not distorted:
        return x, y
    k1, k2, p1, p2, k3 = params[4], params[5], params[6], params[7], params[8]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def _project_point(px: float, py: float, pz: float, params: Array, distorted: bool
                   ) -> tuple[float, float]:
    """``Camera.project`` of one camera-frame point: NaN where ``Z <= 1e-12``."""
    if pz > 1e-12:
        x, y = _distort(px / pz, py / pz, params, distorted)
        return x * params[0] + params[2], y * params[1] + params[3]
    return math.nan, math.nan


def _project(points_cam: Array, params: Array, distorted: bool, out: Array) -> None:
    """``Camera.project`` of (N, 3) camera-frame points into ``out`` (N, 2): NaN where
    ``Z <= 1e-12``."""
    for i in range(points_cam.shape[0]):
        out[i, 0], out[i, 1] = _project_point(points_cam[i, 0], points_cam[i, 1],
                                              points_cam[i, 2], params, distorted)


def _point_jacobian(px: float, py: float, pz: float, params: Array, distorted: bool,
                    out: Array, first_row: int) -> None:
    """Rows ``first_row`` and ``first_row + 1`` of ``out`` (., 6): the pixel Jacobian of one
    camera-frame point w.r.t. a right perturbation of ``world_from_cam`` (radtan's analytic
    pixel Jacobian w.r.t. normalised coordinates, or the pinhole's ``diag(fx, fy)``, through
    ``1 / Z``, then w.r.t. the twist)."""
    fx, fy = params[0], params[1]
    k1, k2, p1, p2, k3 = params[4], params[5], params[6], params[7], params[8]
    inv_z = 1.0 / pz
    x, y = px * inv_z, py * inv_z
    if distorted:
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dxy = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        j00 = fx * (radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x)
        j01 = fx * dxy
        j10 = fy * dxy
        j11 = fy * (radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x)
    else:
        j00, j01, j10, j11 = fx, 0.0, 0.0, fy
    for r in range(2):
        a, b = (j00, j01) if r == 0 else (j10, j11)
        c = -(a * x + b * y)  # d px / d z before the 1 / Z (numpy's einsum)
        a0, a1, a2 = a * inv_z, b * inv_z, c * inv_z
        row = first_row + r
        out[row, 0], out[row, 1], out[row, 2] = -a0, -a1, -a2
        out[row, 3] = a1 * pz - a2 * py
        out[row, 4] = a2 * px - a0 * pz
        out[row, 5] = a0 * py - a1 * px


def _pose_jacobian(points_cam: Array, params: Array, distorted: bool, out: Array) -> None:
    """:func:`~reloc_service.algorithms.pose.projection.pose_jacobian` of (N, 3) camera-frame points into
    ``out`` (2N, 6) (:func:`_point_jacobian` of each)."""
    for i in range(points_cam.shape[0]):
        _point_jacobian(points_cam[i, 0], points_cam[i, 1], points_cam[i, 2], params, distorted,
                        out, 2 * i)


def _opencv_undistort(u: float, v: float, params: Array, iterations: int
                      ) -> tuple[float, float]:
    """``cv2.undistortPoints`` of one distorted normalised point (identity camera matrix,
    radtan coefficients, ``TERM_CRITERIA_COUNT`` of ``iterations``), written as OpenCV's
    C++ computes it: the identity tilt and rectification products included, the six
    unused coefficients as zeros, the start point again where the radial factor turns
    negative (tests compare it with OpenCV on the points of a strong lens)."""
    k0, k1, k2, k3, k4 = params[4], params[5], params[6], params[7], params[8]
    x = (u - 0.0) * 1.0
    y = (v - 0.0) * 1.0
    tz = 0.0 * x + 0.0 * y + 1.0 * 1.0
    inv = 1.0 / tz if tz != 0 else 1.0
    x0 = x = inv * (1.0 * x + 0.0 * y + 0.0 * 1.0)
    y0 = y = inv * (0.0 * x + 1.0 * y + 0.0 * 1.0)
    for _ in range(iterations):
        r2 = x * x + y * y
        icdist = ((1 + ((0.0 * r2 + 0.0) * r2 + 0.0) * r2)
                  / (1 + ((k4 * r2 + k1) * r2 + k0) * r2))
        if icdist < 0:
            x = (u - 0.0) * 1.0
            y = (v - 0.0) * 1.0
            break
        delta_x = 2 * k2 * x * y + k3 * (r2 + 2 * x * x) + 0.0 * r2 + 0.0 * r2 * r2
        delta_y = k2 * (r2 + 2 * y * y) + 2 * k3 * x * y + 0.0 * r2 + 0.0 * r2 * r2
        x = (x0 - delta_x) * icdist
        y = (y0 - delta_y) * icdist
    ww = 1.0 / (0.0 * x + 0.0 * y + 1.0)
    return (1.0 * x + 0.0 * y + 0.0) * ww, (0.0 * x + 1.0 * y + 0.0) * ww


def _undistort_pixels(px: Array, params: Array, opencv_iterations: int,
                      newton_iterations: int, out: Array) -> None:
    """``RadTanCamera.undistort_pixels`` of (N, 2) pixels into ``out``: normalised, OpenCV's
    fixed-point start (:func:`_opencv_undistort`; the target itself where that is not
    finite), then the Newton iterations of ``RadTanCamera.undistort``: every point steps
    in every iteration, until the largest step (NaN ignored) is below 1e-15; back to
    pixels."""
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    k1, k2, p1, p2, k3 = params[4], params[5], params[6], params[7], params[8]
    n = px.shape[0]
    target = np.empty((n, 2))
    for i in range(n):
        tx, ty = (px[i, 0] - cx) / fx, (px[i, 1] - cy) / fy
        target[i, 0], target[i, 1] = tx, ty
        gx, gy = _opencv_undistort(tx, ty, params, opencv_iterations)
        out[i, 0] = gx if math.isfinite(gx) else tx
        out[i, 1] = gy if math.isfinite(gy) else ty
    for _ in range(newton_iterations):
        largest = 0.0
        for i in range(n):
            x, y = out[i, 0], out[i, 1]
            dx, dy = _distort(x, y, params, True)
            res0, res1 = dx - target[i, 0], dy - target[i, 1]
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            a = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
            b = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
            d = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
            det = a * d - b * b
            if abs(det) < 1e-12:
                det = 1e-12
            s0 = (d * res0 - b * res1) / det
            s1 = (-b * res0 + a * res1) / det
            out[i, 0], out[i, 1] = x - s0, y - s1
            if not math.isnan(s0):
                largest = max(largest, abs(s0))
            if not math.isnan(s1):
                largest = max(largest, abs(s1))
        if largest < 1e-15:
            break
    for i in range(n):
        out[i, 0] = out[i, 0] * fx + cx
        out[i, 1] = out[i, 1] * fy + cy


def _moved_points(points: Array, origins: Array, sigmas: Array, out: Array) -> None:
    """``PointUncertainty.pixel_sigmas``' moved points into ``out`` (N, 3): each point moved
    ``sigmas`` along its unit ray from ``origins`` (the norm's squares summed in order)."""
    for i in range(points.shape[0]):
        r0 = points[i, 0] - origins[i, 0]
        r1 = points[i, 1] - origins[i, 1]
        r2 = points[i, 2] - origins[i, 2]
        norm = max(math.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-12)
        out[i, 0] = points[i, 0] + sigmas[i] * (r0 / norm)
        out[i, 1] = points[i, 1] + sigmas[i] * (r1 / norm)
        out[i, 2] = points[i, 2] + sigmas[i] * (r2 / norm)


def _pixel_distances(a: Array, b: Array, out: Array) -> None:
    """(N,) distances between the pixels ``a`` and ``b`` (N, 2) into ``out``; inf where not
    finite."""
    for i in range(a.shape[0]):
        dx, dy = a[i, 0] - b[i, 0], a[i, 1] - b[i, 1]
        d = math.sqrt(dx * dx + dy * dy)
        out[i] = d if math.isfinite(d) else math.inf


def _fit(cam_from_world: Array, px: Array, points: Array, params: Array, distorted: bool,
         threshold: float, origins: Array, depth_sigmas: Array, scales: Array,
         keypoint_sigma: float, projected: Array, inliers: npt.NDArray[np.int64],
         normal: Array, rhs: Array, sums: Array) -> int:
    """The inliers of the pose ``cam_from_world`` and their weighted normal equations, in one
    pass over the N correspondences (``px`` (N, 2) pixels of ``points`` (N, 3)): what
    :func:`~reloc_service.algorithms.pose.pnp._fit_numpy` computes with a dozen array operations.

    Each point is projected (``projected`` (N, 2)); those within ``threshold`` pixels of their
    keypoint are the inliers (their indices, ascending, into ``inliers``; returns how many).
    An inlier's weight is ``1 / (c^2 + (s / keypoint_sigma)^2)``: ``c`` its keypoint's scale
    (``scales``, or 1 where empty), ``s`` the pixels between its projection and that of the
    point moved ``depth_sigmas`` along its ray from ``origins`` (0 where both are empty).
    ``normal`` (6, 6) and ``rhs`` (6,) get ``J^T W J`` and ``J^T W r`` of the residuals
    ``r = px - projected`` (:func:`_point_jacobian`); ``sums`` (2,) gets ``sum w r^2`` and
    ``sum r^2``. The same arithmetic per point as the numpy path; the sums are accumulated
    in point order (so equal to its BLAS products to rounding, not to the bit)."""
    jac = np.empty((2, 6))
    normal[:, :] = 0.0
    rhs[:] = 0.0
    sums[:] = 0.0
    use_depth, use_scales = origins.shape[0] > 0, scales.shape[0] > 0
    count = 0
    for i in range(points.shape[0]):
        c = _transformed(cam_from_world, points[i, 0], points[i, 1], points[i, 2])
        u, v = _project_point(c[0], c[1], c[2], params, distorted)
        projected[i, 0], projected[i, 1] = u, v
        r0, r1 = px[i, 0] - u, px[i, 1] - v
        err = math.sqrt(r0 * r0 + r1 * r1)
        if not err < threshold:  # NaN (behind the camera, or a NaN keypoint) never counts
            continue
        inliers[count] = i
        count += 1
        own = scales[i] ** 2 if use_scales else 1.0
        weight = 1.0 / own
        if use_depth:
            o0 = points[i, 0] - origins[i, 0]
            o1 = points[i, 1] - origins[i, 1]
            o2 = points[i, 2] - origins[i, 2]
            norm = max(math.sqrt(o0 * o0 + o1 * o1 + o2 * o2), 1e-12)
            m = _transformed(cam_from_world, points[i, 0] + depth_sigmas[i] * (o0 / norm),
                             points[i, 1] + depth_sigmas[i] * (o1 / norm),
                             points[i, 2] + depth_sigmas[i] * (o2 / norm))
            mu, mv = _project_point(m[0], m[1], m[2], params, distorted)
            s = math.sqrt((mu - u) * (mu - u) + (mv - v) * (mv - v))
            s = s if math.isfinite(s) else math.inf
            weight = 1.0 / (own + (s / keypoint_sigma) ** 2)
        _point_jacobian(c[0], c[1], c[2], params, distorted, jac, 0)
        for a in range(6):
            ja0, ja1 = weight * jac[0, a], weight * jac[1, a]
            rhs[a] += ja0 * r0 + ja1 * r1
            for b in range(a, 6):
                normal[a, b] += ja0 * jac[0, b] + ja1 * jac[1, b]
        sums[0] += weight * (r0 * r0 + r1 * r1)
        sums[1] += r0 * r0 + r1 * r1
    for a in range(6):
        for b in range(a):
            normal[a, b] = normal[b, a]
    return count


def _cholesky(normal: Array, low: Array) -> bool:
    """``low`` (n, n) = the lower Cholesky factor of ``normal``; False where ``normal`` is
    not positive definite (a pivot not above 1e-12 times the largest diagonal term, or not
    finite): the caller then takes LAPACK's answer."""
    n = normal.shape[0]
    low[:, :] = 0.0
    floor = 0.0
    for i in range(n):
        floor = max(floor, abs(normal[i, i]))
    floor *= 1e-12
    for j in range(n):
        d = normal[j, j]
        for k in range(j):
            d -= low[j, k] * low[j, k]
        if not d > floor:  # NaN included
            return False
        low[j, j] = math.sqrt(d)
        for i in range(j + 1, n):
            v = normal[i, j]
            for k in range(j):
                v -= low[i, k] * low[j, k]
            low[i, j] = v / low[j, j]
    return True


def _solve_factored(low: Array, rhs: Array, out: Array) -> None:
    """``out`` = the solution of ``L L^T x = rhs`` given the Cholesky factor ``L``."""
    n = low.shape[0]
    for i in range(n):  # L y = rhs
        v = rhs[i]
        for k in range(i):
            v -= low[i, k] * out[k]
        out[i] = v / low[i, i]
    for i in range(n - 1, -1, -1):  # L^T x = y
        v = out[i]
        for k in range(i + 1, n):
            v -= low[k, i] * out[k]
        out[i] = v / low[i, i]


def _se3_exp_into(xi: Array, out: Array) -> None:
    """``out`` (4, 4) = ``geometry.se3_exp(xi)``: Rodrigues' rotation and the left Jacobian
    times the translation part, their coefficients from Taylor series below 1e-4 rad
    (where ``1 - cos`` cancels)."""
    w0, w1, w2 = xi[3], xi[4], xi[5]
    theta2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = math.sqrt(theta2)
    if theta < 1e-4:
        a = 1.0 - theta2 / 6.0            # sin(t) / t
        b = 0.5 - theta2 / 24.0           # (1 - cos(t)) / t^2
        c = 1.0 / 6.0 - theta2 / 120.0    # (t - sin(t)) / t^3
    else:
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / theta2
        c = (theta - math.sin(theta)) / (theta2 * theta)
    k = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    k2 = k @ k
    for i in range(3):
        t = 0.0
        for j in range(3):
            eye = 1.0 if i == j else 0.0
            out[i, j] = eye + a * k[i, j] + b * k2[i, j]
            t += (eye + b * k[i, j] + c * k2[i, j]) * xi[j]
        out[i, 3] = t
        out[3, i] = 0.0
    out[3, 3] = 1.0


def _gauss_newton_update(world_from_cam: Array, normal: Array, rhs: Array, step: Array,
                         out: Array) -> bool:
    """One Gauss-Newton update of the normal equations (:func:`_fit`): ``step`` (6,) their
    solution (:func:`_cholesky`), ``out`` = ``world_from_cam @ se3_exp(step)``; False
    (nothing written to ``out``) where they are not positive definite."""
    low = np.empty((6, 6))
    if not _cholesky(normal, low):
        return False
    _solve_factored(low, rhs, step)
    delta = np.empty((4, 4))
    _se3_exp_into(step, delta)
    for i in range(4):
        for j in range(4):
            v = 0.0
            for k in range(4):
                v += world_from_cam[i, k] * delta[k, j]
            out[i, j] = v
    return True


def _spd_inverse(normal: Array, out: Array) -> bool:
    """``out`` = the inverse of the (n, n) ``normal`` matrix: one Cholesky factorisation,
    then a solve per column; False where it is not positive definite."""
    n = normal.shape[0]
    low = np.empty((n, n))
    if not _cholesky(normal, low):
        return False
    unit, column = np.zeros(n), np.empty(n)
    for j in range(n):
        unit[:] = 0.0
        unit[j] = 1.0
        _solve_factored(low, unit, column)
        out[:, j] = column
    return True


def _transformed(a_from_b: Array, x: float, y: float, z: float) -> tuple[float, float, float]:
    """``transform_points`` of one point."""
    return (a_from_b[0, 0] * x + a_from_b[0, 1] * y + a_from_b[0, 2] * z + a_from_b[0, 3],
            a_from_b[1, 0] * x + a_from_b[1, 1] * y + a_from_b[1, 2] * z + a_from_b[1, 3],
            a_from_b[2, 0] * x + a_from_b[2, 1] * y + a_from_b[2, 2] * z + a_from_b[2, 3])


def _pairs_within(projected_px: Array, px: Array, threshold_px: float, threshold_sq: float
                  ) -> int:
    """:func:`~reloc_service.algorithms.pose.chance._pairs_within`: pairs ``j != i`` with
    ``|projected_px[j] - px[i]| < threshold_px`` (per axis differences, squares summed),
    measured only where the x coordinates lie within twice the threshold (a superset);
    ``threshold_sq`` is Python's ``threshold_px**2``."""
    order = np.argsort(px[:, 0], kind="mergesort")
    xs = px[order, 0]
    count = 0
    for j in range(projected_px.shape[0]):
        lo = np.searchsorted(xs, projected_px[j, 0] - 2.0 * threshold_px, side="left")
        hi = np.searchsorted(xs, projected_px[j, 0] + 2.0 * threshold_px, side="right")
        for k in range(lo, hi):
            i = order[k]
            dx = projected_px[j, 0] - px[i, 0]
            dy = projected_px[j, 1] - px[i, 1]
            if dx * dx + dy * dy < threshold_sq and i != j:
                count += 1
    return count


def _best_per_row(rows: npt.NDArray[np.int64], dist: npt.NDArray[np.float32],
                  best: npt.NDArray[np.int64], keep: npt.NDArray[np.int64]) -> int:
    """``landmark_matches.best_per_landmark`` over pool rows (one per landmark): for each row the match
    of the smallest distance, the first of equal ones (a stable sort's choice); their
    indices, ascending, into ``keep``; returns how many. ``best`` (pool size,) holds -1."""
    for k in range(rows.shape[0]):
        r = rows[k]
        if best[r] < 0 or dist[k] < dist[best[r]]:
            best[r] = k
    count = 0
    for k in range(rows.shape[0]):
        if best[rows[k]] == k:
            keep[count] = k
            count += 1
    return count


class Kernels(NamedTuple):
    """The compiled functions (see the module's doc)."""

    project: Callable[..., None]
    pose_jacobian: Callable[..., None]
    undistort_pixels: Callable[..., None]
    moved_points: Callable[..., None]
    pixel_distances: Callable[..., None]
    pairs_within: Callable[..., int]
    best_per_row: Callable[..., int]
    fit: Callable[..., int]
    gauss_newton_update: Callable[..., bool]
    spd_inverse: Callable[..., bool]


@compile_once
def compiled() -> Kernels | None:
    """The kernels compiled by numba (cached on disk by numba after the first compile), or
    None where numba is not installed."""
    # the kernels call the compiled helpers by these names
    global _distort, _opencv_undistort, _project_point, _point_jacobian, _transformed
    global _cholesky, _solve_factored, _se3_exp_into
    numba = numba_or_none()
    if numba is None:
        return None
    _distort = numba.njit(cache=True, nogil=True, inline="always")(_distort)
    _opencv_undistort = numba.njit(cache=True, nogil=True)(_opencv_undistort)
    _project_point = numba.njit(cache=True, nogil=True)(_project_point)
    _point_jacobian = numba.njit(cache=True, nogil=True)(_point_jacobian)
    _transformed = numba.njit(cache=True, nogil=True)(_transformed)
    _cholesky = numba.njit(cache=True, nogil=True)(_cholesky)
    _solve_factored = numba.njit(cache=True, nogil=True)(_solve_factored)
    _se3_exp_into = numba.njit(cache=True, nogil=True)(_se3_exp_into)
    jit: Any = numba.njit(cache=True, nogil=True)
    return Kernels(jit(_project), jit(_pose_jacobian), jit(_undistort_pixels),
                   jit(_moved_points), jit(_pixel_distances), jit(_pairs_within),
                   jit(_best_per_row), jit(_fit), jit(_gauss_newton_update),
                   jit(_spd_inverse))


def camera_params(camera: Any) -> tuple[Array, bool] | None:
    """(fx fy cx cy k1 k2 p1 p2 k3, distorted) of a pinhole or radtan camera, the kernels'
    description of it; None for other models (the numpy path serves them)."""
    if camera.model == "pinhole":
        return np.array([camera.fx, camera.fy, camera.cx, camera.cy, 0.0, 0.0, 0.0, 0.0, 0.0]), False
    if camera.model == "radtan":
        k1, k2, p1, p2, *rest = camera.distortion
        return np.array([camera.fx, camera.fy, camera.cx, camera.cy, k1, k2, p1, p2,
                         rest[0] if rest else 0.0]), True
    return None


def warm_up() -> None:
    """Load (or compile) every kernel now, on a few points: a service worker calls this at
    start so that its first query does not pay numba's import and cache load."""
    k = compiled()
    if k is None:
        return
    params = np.array([500.0, 500.0, 320.0, 240.0, -0.2, 0.05, 1e-4, -1e-4, 0.0])
    pts = np.array([[0.1, -0.2, 2.0], [0.3, 0.1, 3.0], [-0.2, 0.2, 4.0]])
    px, jac, sig = np.empty((3, 2)), np.empty((6, 6)), np.empty(3)
    for distorted in (False, True):
        k.project(pts, params, distorted, px)
        k.pose_jacobian(pts, params, distorted, jac)
    k.undistort_pixels(px, params, 40, 30, np.empty((3, 2)))
    k.moved_points(pts, pts[::-1].copy(), np.ones(3), np.empty((3, 3)))
    k.pixel_distances(px, px, sig)
    k.pairs_within(px, px, 5.0, 25.0)
    k.best_per_row(np.array([0, 1, 0]), np.ones(3, np.float32), np.full(2, -1), np.empty(3, np.int64))
    k.fit(np.eye(4), px, pts, params, True, 5.0, pts[::-1].copy(), np.ones(3), np.ones(3), 1.0,
          np.empty((3, 2)), np.empty(3, np.int64), np.empty((6, 6)), np.empty(6), np.empty(2))
    k.gauss_newton_update(np.eye(4), np.eye(6), np.ones(6), np.empty(6), np.empty((4, 4)))
    k.spd_inverse(np.eye(6), np.empty((6, 6)))
    guided_kernels.warm_up()
    keypoint_grid.warm_up()
    intrinsics_kernels.warm_up()
    repetition_kernels.warm_up()

