"""PnP solve (thesis 3.1.3, improved): P3P in LO-RANSAC (PoseLib) on ideal pinhole pixels,
refined by weighted Gauss-Newton through the real camera model, with the inliers'
reprojection RMS, a 6x6 covariance and the chance that a wrong pose gathers as many inliers
(:func:`.chance.chance_agreement`) as evidence for verification. Where numba is installed (the
``[jit]`` extra) projection, Jacobian and undistortion run as :mod:`.kernels`, the same values,
and each pose's inliers and normal equations come from one compiled pass (:func:`_fit_at`),
the same to rounding.

Used by the P3P pose finder (:mod:`.p3p`, query features matched to landmarks) and by the
ferns relocalizer (classified keypoints)."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import poselib

from ...core.cameras import Camera
from ...core.errors import GeometryError
from ...core.geometry import invert, se3_exp, transform_points
from .base import PoseEstimate
from .cell_sandwich import cell_sandwich, grid_cells, point_sandwich
from .chance import chance_agreement
from .gate_truncation import untruncated_variance
from .intrinsics import CLUSTER_GRID, FOCAL_STARTS, IntrinsicsCheck, check_intrinsics
from .kernels import compiled
from .pnp_conf import PnPConf
from .point_uncertainty import PointUncertainty
from .projection import kernel_camera, pose_jacobian, pose_projector, project_cam, undistort_pixels

Array = npt.NDArray[np.float64]


def solve_pnp(query_px: npt.ArrayLike, points_world: npt.ArrayLike, camera: Camera,
              conf: PnPConf | None = None) -> PoseEstimate | None:
    """Robust ``world_from_cam`` from (N, 2) distorted query pixels and their (N, 3) world
    points; None with fewer than 4 usable correspondences or no RANSAC consensus.

    The pixels are undistorted to the ideal pinhole camera with the same K, so PoseLib sees a
    PINHOLE camera whatever the model; the result is then refined and judged through the real
    model. ``keyframe_ids`` of the estimate is empty (the caller knows them).
    """
    solved = solve_pnp_indexed(query_px, points_world, camera, conf)
    return None if solved is None else solved[0]


@dataclass(frozen=True, eq=False)
class _View:
    """N world points seen from one ``world_from_cam``: (N, 3) camera-frame points and their
    (N, 2) pixels, computed once per pose for the inlier test, the Gauss-Newton residuals,
    the weights and the covariance (each used to project the points anew)."""

    world_from_cam: Array
    points_cam: Array
    px: Array

    @classmethod
    def at(cls, world_from_cam: Array, points_world: Array, camera: Camera) -> _View:
        points_cam = transform_points(invert(world_from_cam), points_world)
        return cls(world_from_cam, points_cam, project_cam(camera, points_cam))

    def inliers(self, px: Array, conf: PnPConf) -> npt.NDArray[np.int64]:
        """Indices whose reprojection error (real camera model) is below the threshold."""
        kernels = compiled()
        if kernels is not None:  # the same distances (inf where not finite: never below)
            err = np.empty(len(px))
            kernels.pixel_distances(np.ascontiguousarray(px, np.float64),
                                    np.ascontiguousarray(self.px), err)
            return np.flatnonzero(err < conf.max_reproj_error_px)
        with np.errstate(invalid="ignore"):
            err = np.linalg.norm(px - self.px, axis=1)
            return np.flatnonzero(err < conf.max_reproj_error_px)

    def residuals_and_jacobian(self, px: Array, rows: npt.NDArray[np.int64], camera: Camera
                               ) -> tuple[Array, Array]:
        """(M, 2) residuals ``px - projection`` of points ``rows`` (``px`` their pixels) and
        their (2M, 6) Jacobian w.r.t. a right perturbation ``world_from_cam @ exp(xi)``,
        ``xi = (rho, omega)``."""
        return px - self.px[rows], pose_jacobian(camera, self.points_cam[rows])


def solve_pnp_indexed(query_px: npt.ArrayLike, points_world: npt.ArrayLike, camera: Camera,
                      conf: PnPConf | None = None, *,
                      uncertainty: PointUncertainty | None = None,
                      keypoint_scales: Array | None = None
                      ) -> tuple[PoseEstimate, npt.NDArray[np.int64]] | None:
    """:func:`solve_pnp`, also returning the (I,) indices of the inlier correspondences. With
    ``uncertainty`` (of the N points), each residual is weighted by how precisely its point is
    known as seen from the pose: an uncertain point still constrains the rotation. With
    ``keypoint_scales`` (N,), keypoint i's localisation noise is ``keypoint_sigma_px`` times
    its scale (the pyramid level's, see :func:`level_scales`); without, every keypoint's is
    ``keypoint_sigma_px``."""
    conf = conf or PnPConf()
    start = time.perf_counter()
    px = np.asarray(query_px, dtype=np.float64).reshape(-1, 2)
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    if len(px) != len(pts):
        raise GeometryError(f"solve_pnp: expected as many points as pixels, "
                            f"got {len(pts)} and {len(px)}")
    ideal_px = undistort_pixels(camera, px)
    usable = np.flatnonzero(np.isfinite(ideal_px).all(1) & np.isfinite(pts).all(1))
    if len(usable) < 4:
        return None
    world_from_cam = ransac_pinhole(ideal_px[usable], pts[usable], camera, conf)
    if world_from_cam is None:
        return None
    scales = None if keypoint_scales is None else np.asarray(keypoint_scales, np.float64)
    return refined_estimate(world_from_cam, px, pts, camera, conf, uncertainty, scales,
                            start=start)


def refined_estimate(world_from_cam: Array, px: Array, pts: Array, camera: Camera,
                     conf: PnPConf, uncertainty: PointUncertainty | None = None,
                     scales: Array | None = None, *, start: float | None = None
                     ) -> tuple[PoseEstimate, npt.NDArray[np.int64]] | None:
    """What :func:`solve_pnp_indexed` returns for the hypothesis ``world_from_cam`` of the
    (N, 2) pixels ``px`` and (N, 3) world points ``pts``: refined (:func:`_refine`), its
    estimate with covariance, chance and intrinsics test, and its (I,) inlier indices; None
    with fewer than 4 inliers. ``start``: ``time.perf_counter()`` when the solve began."""
    start = time.perf_counter() if start is None else start
    fit = _refine(world_from_cam, px, pts, camera, conf, uncertainty, scales)
    if len(fit.inliers) < 4:
        return None
    inliers = fit.inliers
    est = _estimate(fit, px[inliers], pts[inliers], camera, conf, len(px),
                    time.perf_counter() - start)
    est.inlier_sigmas_m = _point_sigmas(fit.world_from_cam, pts[inliers], camera, conf,
                                        None if uncertainty is None
                                        else uncertainty.depth_sigmas_m[inliers],
                                        None if scales is None else scales[inliers])
    if conf.intrinsics_false_refusal > 0:
        est.intrinsics_test = functools.partial(_check_intrinsics, fit, px, pts, camera, conf,
                                                uncertainty, scales)
    scores = functools.cache(functools.partial(_inlier_scores, fit, px, pts, camera, conf,
                                               uncertainty, scales))
    if conf.stated_cell_sandwich:
        cells = functools.partial(grid_cells, px[inliers], camera.size, CLUSTER_GRID)
        est.measurement_sandwich = functools.cache(
            lambda: cell_sandwich(*scores()[:2], cells()))
    if conf.stated_point_sandwich:
        est.point_sandwich = functools.cache(lambda: point_sandwich(*scores()))
    if conf.stated_gate_truncation:
        est.gate_truncation = functools.cache(functools.partial(
            _gate_truncation, fit, pts, camera, conf, uncertainty, scales))
    return est, inliers


def _gate_truncation(fit: _Fit, points_world: Array, camera: Camera, conf: PnPConf,
                     uncertainty: PointUncertainty | None, keypoint_scales: Array | None
                     ) -> Array | None:
    """(6, 6) ``(sigma_u^2 - sigma^2) (J^T W J)^-1``: the untruncated keypoint variance of
    ``fit``'s inliers (:func:`.gate_truncation.untruncated_variance`) less the one its
    covariance states (:func:`_estimate`); None where it adds nothing or is unknown."""
    weights = _weights(fit.world_from_cam, points_world, fit.inliers, camera, conf,
                       uncertainty, keypoint_scales)
    untruncated = untruncated_variance(weights, fit.weighted_sq, conf.max_reproj_error_px)
    stated = max(fit.weighted_sq / max(2 * len(fit.inliers) - 6, 1), conf.min_sigma_px**2)
    if not np.isfinite(untruncated) or untruncated <= stated:
        return None
    extra = (untruncated - stated) * _normal_inverse(fit.normal)
    return extra if np.all(np.isfinite(extra)) else None


def _inlier_scores(fit: _Fit, px: Array, points_world: Array, camera: Camera, conf: PnPConf,
                   uncertainty: PointUncertainty | None, keypoint_scales: Array | None
                   ) -> tuple[Array, Array, Array]:
    """The (6, 6) inverse normal matrix of ``fit``, its inliers' (I, 6) weighted scores
    ``J_i^T W_i r_i`` and (I, 6, 6) informations ``J_i^T W_i J_i``, with the refinement's
    weights: what :mod:`.cell_sandwich` compares the model covariance with, by cell or by
    point."""
    rows = fit.inliers
    weights = _weights(fit.world_from_cam, points_world, rows, camera, conf, uncertainty,
                       keypoint_scales)
    points_cam = transform_points(invert(fit.world_from_cam), points_world[rows])
    jac = pose_jacobian(camera, points_cam).reshape(-1, 2, 6)
    scores = np.einsum("nki,nk->ni", jac, px[rows] - fit.projected_px) * weights[:, None]
    informations = np.einsum("nki,nkj->nij", jac, jac) * weights[:, None, None]
    return _normal_inverse(fit.normal), scores, informations


def _check_intrinsics(fit: _Fit, px: Array, points_world: Array, camera: Camera,
                      conf: PnPConf, uncertainty: PointUncertainty | None,
                      keypoint_scales: Array | None, *,
                      focal_starts: tuple[float, ...] = FOCAL_STARTS,
                      rows: npt.NDArray[np.int64] | None = None) -> IntrinsicsCheck | None:
    """:func:`.intrinsics.check_intrinsics` of ``camera`` on every correspondence of ``fit``
    (or on those of ``rows`` alone, ascending), with the refinement's weights (from
    ``focal_starts`` besides the given focal)."""
    rows = np.arange(len(points_world)) if rows is None else np.asarray(rows, np.int64)
    weights = _weights(fit.world_from_cam, points_world, rows, camera, conf, uncertainty,
                       keypoint_scales)
    inliers = np.flatnonzero(np.isin(rows, fit.inliers))  # positions within ``rows``
    if len(inliers) == 0:
        return None
    depths = transform_points(invert(fit.world_from_cam), points_world[rows[inliers]])[:, 2]
    return check_intrinsics(fit.world_from_cam, px[rows], inliers, weights, camera,
                            pose_projector(points_world[rows], camera),
                            depth_m=float(np.median(depths)),
                            threshold_px=conf.max_reproj_error_px,
                            min_sigma_px=conf.min_sigma_px, prior=conf.intrinsics_prior,
                            focal_starts=focal_starts)


def level_scales(levels: npt.NDArray[np.integer], scale_factor: float) -> Array:
    """(N,) scale of keypoints found at pyramid ``levels`` with ``scale_factor`` between
    levels: a level-l keypoint is located to a pixel of the level-l image, ``factor^l``
    pixels of the full image (ORB-SLAM's ``sigma^2 = factor^(2 l)``)."""
    return np.power(float(scale_factor), np.asarray(levels, np.float64))


def _point_sigmas(world_from_cam: Array, points_world: Array, camera: Camera, conf: PnPConf,
                  depth_sigmas_m: Array | None, keypoint_scales: Array | None = None) -> Array:
    """(N,) 1-sigma position uncertainty of world points, metres: their depth uncertainty,
    at least the ``keypoint_sigma_px`` (times the keypoint's scale) of a keypoint at their
    range from ``world_from_cam``."""
    ranges = np.linalg.norm(points_world - world_from_cam[:3, 3], axis=1)
    floor = ranges * conf.keypoint_sigma_px / max(camera.fx, camera.fy)
    if keypoint_scales is not None:
        floor = floor * keypoint_scales
    return floor if depth_sigmas_m is None else np.maximum(depth_sigmas_m, floor)


def _weights(world_from_cam: Array, points_world: Array, rows: npt.NDArray[np.int64],
             camera: Camera, conf: PnPConf, uncertainty: PointUncertainty | None,
             keypoint_scales: Array | None = None, *, view: _View | None = None) -> Array:
    """(M,) residual weights of points ``rows``: ``1 / (1 + (s / keypoint_sigma)^2)`` with
    ``s`` their depth uncertainty in the query's pixels (ones without ``uncertainty``); with
    ``keypoint_scales`` ``c``, ``1 / (c^2 + (s / keypoint_sigma)^2)``: the inverse variance
    in units of a level-0 keypoint's. ``view``: the points seen from ``world_from_cam``,
    when already projected."""
    if uncertainty is None:
        if keypoint_scales is None:
            return np.ones(len(rows))
        return 1.0 / keypoint_scales[rows] ** 2
    s = uncertainty.pixel_sigmas(world_from_cam, points_world[rows], camera, rows,
                                 projected_px=None if view is None else view.px[rows])
    own = 1.0 if keypoint_scales is None else keypoint_scales[rows] ** 2
    return 1.0 / (own + (s / conf.keypoint_sigma_px) ** 2)


def ransac_pinhole(ideal_px: Array, points_world: Array, camera: Camera, conf: PnPConf
                   ) -> Array | None:
    """PoseLib P3P LO-RANSAC (with its own refinement) on (N, 2) pixels of the ideal pinhole
    camera with ``camera``'s K and (N, 3) world points; ``world_from_cam`` or None."""
    camera_dict = {"model": "PINHOLE", "width": camera.width, "height": camera.height,
                   "params": [camera.fx, camera.fy, camera.cx, camera.cy]}
    ransac_opt = {"max_reproj_error": conf.max_reproj_error_px,
                  "min_iterations": conf.min_iterations, "max_iterations": conf.max_iterations,
                  "success_prob": conf.success_prob, "seed": conf.seed}
    pose, info = poselib.estimate_absolute_pose(ideal_px, points_world, camera_dict, ransac_opt, {})
    if info["num_inliers"] < 4:
        return None
    cam_from_world = np.eye(4)
    cam_from_world[:3, :] = pose.Rt  # PoseLib's pose maps world points into the camera
    if not np.all(np.isfinite(cam_from_world)):
        return None
    return invert(cam_from_world)


@dataclass(frozen=True, eq=False)
class _Fit:
    """The inliers of one ``world_from_cam`` (reprojection error through the real camera model
    below the threshold) and their weighted normal equations: ``normal = J^T W J`` (6, 6)
    and ``rhs = J^T W r`` (6,) of the residuals ``r = px - projected``, the weights of
    :func:`_weights`; ``weighted_sq = sum w r^2`` and ``sq = sum r^2``. One pass over the
    points gives the Gauss-Newton step, the covariance and the RMS of a pose."""

    world_from_cam: Array
    inliers: npt.NDArray[np.int64]
    projected_px: Array  # (I, 2) the inliers' points at world_from_cam
    normal: Array
    rhs: Array
    weighted_sq: float
    sq: float


def _fit_at(world_from_cam: Array, px: Array, points_world: Array, camera: Camera,
            conf: PnPConf, uncertainty: PointUncertainty | None = None,
            keypoint_scales: Array | None = None) -> _Fit:
    """:class:`_Fit` of ``world_from_cam``: compiled in one pass for pinhole and radtan
    cameras where numba is installed (:func:`.kernels._fit`, the same values to rounding),
    else :func:`_fit_numpy`."""
    kernels, params = compiled(), kernel_camera(camera)
    if kernels is None or params is None:
        return _fit_numpy(world_from_cam, px, points_world, camera, conf, uncertainty,
                          keypoint_scales)
    n = len(points_world)
    projected, inliers = np.empty((n, 2)), np.empty(n, np.int64)
    normal, rhs, sums = np.empty((6, 6)), np.empty(6), np.empty(2)
    empty = np.empty((0, 3))
    count = kernels.fit(
        invert(world_from_cam), np.ascontiguousarray(px, np.float64),
        np.ascontiguousarray(points_world, np.float64), params[0], params[1],
        float(conf.max_reproj_error_px),
        empty if uncertainty is None else np.ascontiguousarray(uncertainty.ray_origins_world,
                                                               np.float64),
        empty[:, 0] if uncertainty is None else np.ascontiguousarray(uncertainty.depth_sigmas_m,
                                                                     np.float64),
        empty[:, 0] if keypoint_scales is None else np.ascontiguousarray(keypoint_scales,
                                                                         np.float64),
        float(conf.keypoint_sigma_px), projected, inliers, normal, rhs, sums)
    inliers = inliers[:count]
    return _Fit(world_from_cam, inliers, projected[inliers], normal, rhs, float(sums[0]),
                float(sums[1]))


def _fit_numpy(world_from_cam: Array, px: Array, points_world: Array, camera: Camera,
               conf: PnPConf, uncertainty: PointUncertainty | None = None,
               keypoint_scales: Array | None = None) -> _Fit:
    """:class:`_Fit` of ``world_from_cam`` from array operations: the points projected
    once (:class:`_View`), the inliers, their residuals, Jacobian and weights."""
    view = _View.at(world_from_cam, points_world, camera)
    inliers = view.inliers(px, conf)
    residual, jac = view.residuals_and_jacobian(px[inliers], inliers, camera)
    w = _weights(world_from_cam, points_world, inliers, camera, conf, uncertainty,
                 keypoint_scales, view=view)
    weighted = jac * np.repeat(w, 2)[:, None]
    return _Fit(world_from_cam, inliers, view.px[inliers], weighted.T @ jac,
                weighted.T @ residual.ravel(), float((w[:, None] * residual**2).sum()),
                float((residual**2).sum()))


def _refine(world_from_cam: Array, px: Array, points_world: Array, camera: Camera,
            conf: PnPConf, uncertainty: PointUncertainty | None = None,
            keypoint_scales: Array | None = None) -> _Fit:
    """Gauss-Newton on the inliers' reprojection error (weighted, see :func:`_weights`)
    through the real camera model; returns the :class:`_Fit` of the refined pose.

    Not ``poselib.refine_absolute_pose``: with a TRIVIAL loss it reaches the same pose
    unweighted, but PoseLib 2.0.5 takes no per-residual weights, and the landmarks' depth
    uncertainty needs them. The Jacobian is PoseLib's camera model's (:func:`.projection.pixel_jacobian`)."""
    fit = _fit_at(world_from_cam, px, points_world, camera, conf, uncertainty, keypoint_scales)
    for _ in range(conf.refine_iterations):
        if len(fit.inliers) < 4:
            break
        step, updated = _gauss_newton_update(fit)
        fit = _fit_at(updated, px, points_world, camera, conf, uncertainty, keypoint_scales)
        if np.linalg.norm(step) < 1e-12:
            break
    return fit


def _gauss_newton_update(fit: _Fit) -> tuple[Array, Array]:
    """The (6,) solution ``step`` of ``fit``'s normal equations ``J^T W J x = J^T W r`` and
    ``world_from_cam @ se3_exp(step)``: compiled where numba is installed
    (:func:`.kernels._gauss_newton_update`, Cholesky); else, or where they are not positive
    definite, LAPACK's solve, and where they are singular the minimum-norm least-squares
    step (the pseudo-inverse's: that of the weighted Jacobian's least squares)."""
    kernels = compiled()
    if kernels is not None:
        step, updated = np.empty(6), np.empty((4, 4))
        if kernels.gauss_newton_update(np.ascontiguousarray(fit.world_from_cam, np.float64),
                                       fit.normal, fit.rhs, step, updated):
            return step, updated
    try:
        solved = np.linalg.solve(fit.normal, fit.rhs)
    except np.linalg.LinAlgError:
        solved = np.linalg.lstsq(fit.normal, fit.rhs, rcond=None)[0]
    return np.asarray(solved, np.float64), fit.world_from_cam @ se3_exp(solved)


def _estimate(fit: _Fit, px: Array, points_world: Array, camera: Camera, conf: PnPConf,
              num_matches: int, elapsed: float) -> PoseEstimate:
    """The estimate of ``fit`` (``px`` and ``points_world``: its inliers') with their RMS and
    the weighted Gauss-Newton covariance ``sigma^2 (J^T W J)^-1`` (sigma from the weighted
    residuals, floored at ``min_sigma_px``)."""
    chance = chance_agreement(fit.projected_px, px, conf.max_reproj_error_px, camera.size)
    dof = max(2 * len(px) - 6, 1)
    sigma2 = max(fit.weighted_sq / dof, conf.min_sigma_px**2)
    return PoseEstimate(world_from_cam=fit.world_from_cam, keyframe_ids=[],
                        num_matches=num_matches, inliers=len(px),
                        reprojection_rms_px=float(np.sqrt(fit.sq / len(px))),
                        covariance=sigma2 * _normal_inverse(fit.normal),
                        timings={"solve": elapsed},
                        inlier_px=px.copy(), inlier_points_world=points_world.copy(),
                        image_size=camera.size, inlier_threshold_px=conf.max_reproj_error_px,
                        chance_probability=chance)


def _normal_inverse(normal: Array) -> Array:
    """``(J^T W J)^-1``: compiled where numba is installed (Cholesky), else, or where it is
    not positive definite, LAPACK's inverse; all infinite where singular (degenerate
    geometry: unknown, so infinitely uncertain)."""
    kernels = compiled()
    if kernels is not None:
        out = np.empty((6, 6))
        if kernels.spd_inverse(normal, out):
            return out
    try:
        return np.asarray(np.linalg.inv(normal), np.float64)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)
