"""The intrinsics test's normal equations, compiled and numpy, against the einsum-based
formulation they replace: the same rows, residuals, Jacobians, cost and normal equations, bit
for bit, on a distorted camera, poses and intrinsics errors away from the truth, and points
behind the camera."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.pose import intrinsics, intrinsics_kernels, intrinsics_model
from reloc_service.algorithms.pose.projection import pose_projector
from reloc_service.core.cameras import RadTanCamera
from reloc_service.core.geometry import se3_exp

CAMERA = RadTanCamera(640, 480, 517.3, 516.5, 318.6, 255.3,
                      (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))


def _reference(world_from_cam, theta, px, weights, model, project, threshold_px, rows=None):
    """The normal equations as first written: every row modelled and differentiated (the
    pose Jacobian by einsum), the gated rows taken afterwards."""
    projected, jac = project(world_from_cam)
    a, b = theta
    v = projected - model.centre
    u = v / model.radius_px
    r2 = (u * u).sum(axis=1)
    g = u * r2[:, None]
    pixels = model.centre + (1.0 + a) * v + b * g
    dv = (2.0 * b / model.radius_px) * u[:, :, None] * u[:, None, :]
    diagonal = 1.0 + a + b * r2 / model.radius_px
    dv[:, 0, 0] += diagonal
    dv[:, 1, 1] += diagonal
    d_pose = np.einsum("mij,mjk->mik", dv, jac)
    d_theta = np.stack([v, g], axis=2)
    residuals = px - pixels
    squared = (residuals**2).sum(axis=1)
    squared = np.where(np.isfinite(squared), squared, np.inf)
    if rows is None:
        rows = np.flatnonzero(squared < threshold_px**2)
    cost = float((weights * np.minimum(squared, threshold_px**2)).sum())
    full = np.concatenate([d_pose[rows], d_theta[rows]], axis=2)
    w = weights[rows]
    flat = full.reshape(-1, 8)
    weighted = flat * np.repeat(w, 2)[:, None]
    return rows, weighted.T @ flat, weighted.T @ residuals[rows].ravel(), residuals[rows], full, cost


def _problem(seed: int, n: int = 300):
    rng = np.random.default_rng(seed)
    points_cam = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.1, 1.1, n),
                                  rng.uniform(2.0, 5.0, n)])
    points_cam[:5, 2] = -1.0  # behind the camera: not finite, never gated in
    px = CAMERA.project(np.abs(points_cam)) + rng.normal(0.0, 0.7, (n, 2))
    px[rng.random(n) < 0.3] = rng.uniform(0.0, 480.0, 2)
    return points_cam, px, rng.uniform(0.2, 1.0, n)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("seed", [0, 1])
def test_normal_equations_match_the_einsum_formulation(compiled, seed, monkeypatch):
    if compiled:
        pytest.importorskip("numba")
    else:
        monkeypatch.setattr(intrinsics_kernels, "compiled", lambda: None)
    points, px, weights = _problem(seed)
    model = intrinsics_model.IntrinsicsModel(CAMERA)
    project = pose_projector(points, CAMERA)
    for step, theta in [(np.zeros(6), np.zeros(2)),
                        (np.array([0.002, -0.001, 0.003, 0.0005, -0.0003, 0.0004]),
                         np.array([0.003, -0.002]))]:
        pose = se3_exp(step)
        for rows in (None, np.arange(5, 120, 3)):
            got = intrinsics._normal_equations(pose, theta, px, weights, model, project, 4.0,
                                               rows=rows)
            want = _reference(pose, theta, px, weights, model, project, 4.0, rows=rows)
            assert len(want[0]) > 20
            for a, b in zip((got.rows, got.normal, got.rhs, got.residuals, got.jac),
                            want[:5], strict=True):
                np.testing.assert_array_equal(a, b)
            assert got.cost == want[5]


def test_model_apply_keeps_its_values():
    points, _, _ = _problem(2)
    model = intrinsics_model.IntrinsicsModel(CAMERA)
    projected, jac = pose_projector(points, CAMERA)(np.eye(4))
    theta = np.array([0.05, -0.1])
    pixels, d_pose, d_theta = model.apply(projected, jac, theta)
    # Against zero pixels the reference's residuals are minus its modelled pixels.
    every = np.arange(len(points))
    _, _, _, residuals, full, _ = _reference(np.eye(4), theta, np.zeros_like(projected),
                                             np.ones(len(points)), model,
                                             lambda _: (projected, jac), 1.0, rows=every)
    np.testing.assert_array_equal(pixels, -residuals)
    np.testing.assert_array_equal(d_pose, full[:, :, :6])
    np.testing.assert_array_equal(d_theta, full[:, :, 6:])
