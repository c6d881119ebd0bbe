"""The covariance of a pose whose landmarks come from several keyframes, robust to their
disagreeing: the cluster-robust (sandwich) estimate with one cluster per source keyframe
(Liang & Zeger 1986; Cameron & Miller 2015, eq. 11), and the smallest covariance at least
as large as both it and the model's.

Landmarks triangulated from one keyframe's pose share that pose's error: a map built from
poses a few centimetres off (KinectFusion, motion capture) holds groups of landmarks each
consistent within itself and shifted against the others. A pose solved on several groups
is a compromise whose residuals are correlated within each group, and the Gauss-Newton
covariance, which assumes independent residuals, shrinks with the number of inliers while
the error does not. The sandwich ``H^-1 (sum_g s_g s_g^T) H^-1`` (``s_g`` the score
``J_g^T r_g`` of group g, ``H = J^T J``, scaled by ``G / (G - 1)`` for G groups) measures
the spread the groups actually show."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from .projection import pose_projector

Array = npt.NDArray[np.float64]


def cluster_robust_covariance(world_from_cam: Array, px: Array, points_world: Array,
                              camera: Camera, clusters: npt.NDArray[np.int64]) -> Array | None:
    """(6, 6) sandwich covariance of ``world_from_cam`` (twist convention of
    :func:`.projection.pose_projector`) fitted to (N, 2) pixels ``px`` of (N, 3) ``points_world``,
    the residuals correlated within each of the (N,) ``clusters``; None with fewer than two
    clusters (no spread between groups to measure) or a singular fit."""
    labels, group = np.unique(np.asarray(clusters), return_inverse=True)
    if len(labels) < 2 or len(px) < 4:
        return None
    projected, jac = pose_projector(np.asarray(points_world, np.float64), camera)(world_from_cam)
    residual = np.asarray(px, np.float64) - projected                     # (N, 2)
    if not (np.isfinite(residual).all() and np.isfinite(jac).all()):
        return None
    hessian = np.einsum("nki,nkj->ij", jac, jac)
    scores = np.zeros((len(labels), 6))
    np.add.at(scores, group, np.einsum("nki,nk->ni", jac, residual))
    try:
        bread = np.linalg.inv(hessian)
    except np.linalg.LinAlgError:
        return None
    meat = scores.T @ scores * (len(labels) / (len(labels) - 1.0))
    return np.asarray(bread @ meat @ bread, np.float64)


def at_least(covariance: Array, other: Array) -> Array:
    """The smallest covariance (in the Loewner order, along the whitened axes of
    ``covariance``) that is at least ``covariance`` and at least ``other``: ``other``
    whitened by ``covariance``, its eigenvalues below 1 raised to 1, coloured back.
    ``covariance`` itself where either is not finite (a singular fit states an infinite
    covariance: unknown stays unknown) or ``covariance`` is not positive definite."""
    if not (np.isfinite(covariance).all() and np.isfinite(other).all()):
        return covariance
    values, vectors = np.linalg.eigh(covariance)
    if not np.all(values > 0):
        return covariance
    root = vectors * np.sqrt(values)                                  # covariance = root root^T
    inv_root = np.linalg.inv(root)
    whitened = inv_root @ other @ inv_root.T
    w_values, w_vectors = np.linalg.eigh(0.5 * (whitened + whitened.T))
    lifted = (w_vectors * np.maximum(w_values, 1.0)) @ w_vectors.T
    out = root @ lifted @ root.T
    return np.asarray(0.5 * (out + out.T), np.float64)
