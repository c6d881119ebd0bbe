"""The intrinsics error model's Jacobian is the derivative of its pixels: central differences
of the pose (a right perturbation, through the radtan lens of the data sets) and of the focal
and radial errors agree with it, at the given camera and far from it."""

from __future__ import annotations

import numpy as np
import pytest
from test_pose_intrinsics import POSE, ROOM, correspondences

from reloc_service.algorithms.pose.intrinsics_model import IntrinsicsModel
from reloc_service.algorithms.pose.projection import pose_projector
from reloc_service.core.geometry import se3_exp


def pixels_at(model: IntrinsicsModel, project, world_from_cam: np.ndarray,
              params: np.ndarray) -> np.ndarray:
    """(N, 2) modelled pixels at ``world_from_cam`` moved by the twist ``params[:6]`` (right
    perturbation) with ``theta = params[6:]``."""
    projected, _ = project(world_from_cam @ se3_exp(params[:6]))
    return model.pixels(projected, params[6:])


@pytest.mark.parametrize("theta", [(0.0, 0.0), (-0.38, 28.0), (0.3, -35.0)])
def test_the_jacobian_is_the_derivative_of_the_pixels(theta):
    """Including the focal 38 % short with 28 px of radial error that the ORB inliers of a
    blurred, occluded room-hard query fit at the right camera: the estimate's pull there is
    the data's, not a wrong derivative."""
    _, points = correspondences(ROOM, 50, 0.0, np.random.default_rng(0))
    model, project = IntrinsicsModel(ROOM), pose_projector(points, ROOM)
    theta = np.asarray(theta, np.float64)
    projected, jac = project(POSE)
    analytic = model.jacobian(projected, jac, theta)  # (N, 2, 8)
    base = np.concatenate([np.zeros(6), theta])
    steps = np.array([1e-6] * 6 + [1e-6, 1e-4])
    numeric = np.empty_like(analytic)
    for k, h in enumerate(steps):
        delta = np.zeros(8)
        delta[k] = h
        numeric[:, :, k] = (pixels_at(model, project, POSE, base + delta)
                            - pixels_at(model, project, POSE, base - delta)) / (2 * h)
    scale = np.abs(numeric).max(axis=(0, 1))
    assert np.all(np.abs(analytic - numeric).max(axis=(0, 1)) <= 1e-5 * scale + 1e-7)


def test_the_compiled_jacobian_of_rows_is_the_jacobian_of_those_rows():
    _, points = correspondences(ROOM, 40, 0.0, np.random.default_rng(1))
    model, project = IntrinsicsModel(ROOM), pose_projector(points, ROOM)
    projected, jac = project(POSE)
    rows = np.array([3, 7, 8, 20, 39], np.int64)
    theta = np.array([-0.2, 10.0])
    assert np.allclose(model.jacobian_of(projected, jac, rows, theta),
                       model.jacobian(projected[rows], jac[rows], theta), atol=1e-9)
