"""Re-gated refinement of a pose from a start that carries a covariance (ORB-SLAM's tracking
optimisation, with its gates from the start's covariance instead of a fixed pixel radius).

A correspondence ``i`` whose point projects to ``pi_i(x)`` at the pose ``x`` has, when right,
the residual covariance ``S_i = sigma^2 / w_i I + J_i C J_i^T`` (``sigma^2 / w_i`` its own
pixel noise, :func:`.pnp._weights`; ``J_i C J_i^T`` the spread the pose's covariance ``C``
gives its projection). It is kept while ``r_i^T S_i^-1 r_i <= chi2_2(p)``. Each round keeps
the correspondences inside their gates, takes a weighted Gauss-Newton step on them and
shrinks ``C`` to their own covariance, until the kept set repeats: a pose solved from part of
the image (a few pixels off elsewhere) reaches the right correspondences there, whose
residuals its covariance predicts, where a fixed inlier threshold would leave them out and
keep it in its own basin. The last step is :func:`.pnp.refined_estimate`, so the answer is
gated, weighted and judged as a P3P solve's is.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.geometry import se3_exp
from .base import PoseEstimate
from .pnp import _View, _weights, refined_estimate
from .pnp_conf import PnPConf
from .point_uncertainty import PointUncertainty
from .projection import pose_jacobian

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def covariance_gated(residuals: Array, jac: Array, noise_var: Array, covariance: Array,
                     gate_chi2: float) -> IntArray:
    """Indices of the (N, 2) ``residuals`` inside their chi-square gate ``gate_chi2`` under
    ``S_i = noise_var_i I + J_i C J_i^T`` (``jac`` (N, 2, 6), ``covariance`` C (6, 6),
    ``noise_var`` (N,) pixels^2); a non-finite residual is outside."""
    spread = jac @ covariance @ jac.transpose(0, 2, 1)
    a = spread[:, 0, 0] + noise_var
    c = spread[:, 1, 1] + noise_var
    b = spread[:, 0, 1]
    det = a * c - b * b
    dx, dy = residuals[:, 0], residuals[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        m2 = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det
    return np.flatnonzero(np.isfinite(m2) & (det > 0) & (m2 <= gate_chi2))


def regated_pose(world_from_cam: Array, covariance: Array, sigma2_px: float, px: Array,
                 points_world: Array, camera: Camera, conf: PnPConf,
                 uncertainty: PointUncertainty | None, gate_chi2: float, *,
                 rounds: int = 10) -> Array | None:
    """The pose after the module's rounds from ``world_from_cam`` (covariance (6, 6),
    residual variance per unit weight ``sigma2_px``) on (N, 2) ``px`` and (N, 3)
    ``points_world``; None when a round keeps fewer than 4 or its normal equations are
    singular."""
    rows_all = np.arange(len(points_world))
    pose, cov, sigma2 = world_from_cam, covariance, sigma2_px
    kept: IntArray | None = None
    for _ in range(rounds):
        view = _View.at(pose, points_world, camera)
        jac = pose_jacobian(camera, view.points_cam).reshape(-1, 2, 6)
        w = _weights(pose, points_world, rows_all, camera, conf, uncertainty, view=view)
        residuals = px - view.px
        rows = covariance_gated(residuals, jac, sigma2 / w, cov, gate_chi2)
        if len(rows) < 4:
            return None
        if kept is not None and np.array_equal(rows, kept):
            break
        flat = jac[rows].reshape(-1, 6)
        weighted = flat * np.repeat(w[rows], 2)[:, None]
        normal = weighted.T @ flat
        try:
            step = np.linalg.solve(normal, weighted.T @ residuals[rows].ravel())
            inverse = np.asarray(np.linalg.inv(normal), np.float64)
        except np.linalg.LinAlgError:
            return None
        dof = max(2 * len(rows) - 6, 1)
        sigma2 = max(float((w[rows, None] * residuals[rows] ** 2).sum()) / dof,
                     conf.min_sigma_px**2)
        pose, cov, kept = pose @ se3_exp(step), sigma2 * inverse, rows
    return pose


def refine_from(est: PoseEstimate, px: Array, points_world: Array, camera: Camera,
                conf: PnPConf, uncertainty: PointUncertainty | None, gate_chi2: float
                ) -> tuple[PoseEstimate, IntArray] | None:
    """:func:`regated_pose` from ``est`` (its pose, covariance and reprojection RMS), then
    :func:`.pnp.refined_estimate`: (estimate, (I,) inlier indices) or None."""
    if est.covariance is None or not np.all(np.isfinite(est.covariance)):
        return None
    # The RMS is of the 2-vector residual: half its square is the variance per axis.
    sigma2 = max(0.5 * float(est.reprojection_rms_px or 0.0) ** 2, conf.min_sigma_px**2)
    pose = regated_pose(est.world_from_cam, est.covariance, sigma2, px, points_world, camera,
                        conf, uncertainty, gate_chi2)
    if pose is None:
        return None
    return refined_estimate(pose, px, points_world, camera, conf, uncertainty)
