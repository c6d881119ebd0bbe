"""The intrinsics test's Gauss-Newton run from every start at once, against the start-by-start
loop it replaces (the same steps, halvings and stopping rule): the same rows and estimates to
rounding, compiled and numpy; and its batched twist maps against the single ones."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.pose import intrinsics, intrinsics_kernels
from reloc_service.algorithms.pose.intrinsics_gauss_newton import (
    MAX_HALVINGS,
    MIN_ROWS,
    Problem,
    joint_estimates,
)
from reloc_service.algorithms.pose.intrinsics_model import IntrinsicsModel
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.algorithms.pose.projection import pose_projector
from reloc_service.core.cameras import RadTanCamera
from reloc_service.core.geometry import (
    look_at,
    se3_exp,
    se3_exp_many,
    se3_log,
    se3_log_many,
    transform_points,
)

CAMERA = RadTanCamera(640, 480, 517.3, 516.5, 318.6, 255.3,
                      (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
POSE = look_at([0.4, -0.3, -4.0], [0.1, 0.2, 0.0], up=[0, -1, 0])


def _serial(world_from_cam, theta, rows, problem, iterations):
    """One start's Gauss-Newton as it was written before the starts ran together."""
    p = problem
    eq = intrinsics._normal_equations(world_from_cam, theta, p.px, p.weights, p.model,
                                      p.project, p.threshold_px, rows=rows)
    pose = world_from_cam
    for _ in range(iterations):
        try:
            step = np.linalg.solve(eq.normal, eq.rhs)
        except np.linalg.LinAlgError:
            break
        for _ in range(MAX_HALVINGS):
            trial_pose, trial_theta = pose @ se3_exp(step[:6]), theta + step[6:]
            trial = intrinsics._normal_equations(trial_pose, trial_theta, p.px, p.weights,
                                                 p.model, p.project, p.threshold_px)
            if trial.cost < eq.cost and len(trial.rows) >= MIN_ROWS:
                break
            step = step / 2.0
        else:
            break
        pose, theta, eq = trial_pose, trial_theta, trial
        if np.abs(step[6:] / [1e-4, 1e-2]).max() < 1.0 and np.abs(step[:6]).max() < 1e-6:
            break
    return pose, theta, eq


def _scene(seed: int, focal_scale: float):
    """Pixels of a camera whose focal is ``focal_scale`` times the given one's, with noise
    and 30 % outliers, of world points, with weights; the pose PnP finds for them through
    the given camera and its inliers."""
    rng = np.random.default_rng(seed)
    n = 300
    px = rng.uniform([0, 0], [639, 479], (n, 2))
    bearings = CAMERA.unproject(px)
    points_world = transform_points(POSE, bearings / bearings[:, 2:] * rng.uniform(1.5, 6, n)[:, None])
    centre = np.array([CAMERA.cx, CAMERA.cy])
    px = centre + focal_scale * (px - centre) + rng.normal(0.0, 1.0, (n, 2))
    outliers = rng.random(n) < 0.3
    px[outliers] = rng.uniform([0, 0], [639, 479], (outliers.sum(), 2))
    problem = Problem(px, rng.uniform(0.3, 1.0, n), IntrinsicsModel(CAMERA),
                      pose_projector(points_world, CAMERA), 4.0)
    solved = solve_pnp_indexed(px, points_world, CAMERA, PnPConf())
    assert solved is not None
    return problem, solved[0].world_from_cam, solved[1]


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize(("seed", "focal_scale"), [(0, 1.0), (1, 1.08), (2, 0.9)])
def test_the_starts_together_follow_each_start_alone(compiled, seed, focal_scale, monkeypatch):
    if compiled:
        pytest.importorskip("numba")
    else:
        monkeypatch.setattr(intrinsics_kernels, "compiled", lambda: None)
    problem, pose, inliers = _scene(seed, focal_scale)
    factors = intrinsics.FOCAL_STARTS
    starts = np.stack([pose] + [pose @ intrinsics._along_axis(-(f - 1.0) * 3.0) for f in factors])
    thetas = np.array([[0.0, 0.0]] + [[f - 1.0, 0.0] for f in factors])
    poses, got_thetas, equations = joint_estimates(starts, thetas, inliers, problem, 5)
    want = [_serial(starts[0], thetas[0], inliers, problem, 5)]
    for start, theta in zip(starts[1:], thetas[1:], strict=True):
        if len(intrinsics._normal_equations(start, theta, problem.px, problem.weights,
                                            problem.model, problem.project, 4.0).rows) >= 8:
            want.append(_serial(start, theta, None, problem, 5))
    assert len(want) == len(poses) >= 2
    for pose, theta, eq, (want_pose, want_theta, want_eq) in zip(poses, got_thetas, equations,
                                                                 want, strict=True):
        np.testing.assert_array_equal(eq.rows, want_eq.rows)
        np.testing.assert_allclose(pose, want_pose, rtol=0, atol=1e-9)
        np.testing.assert_allclose(theta, want_theta, rtol=0, atol=1e-9)
        np.testing.assert_allclose(eq.normal, want_eq.normal, rtol=1e-9,
                                   atol=1e-9 * np.abs(want_eq.normal).max())
        np.testing.assert_allclose(eq.cost, want_eq.cost, rtol=1e-9)


def test_the_batched_twist_maps_are_the_single_ones():
    rng = np.random.default_rng(0)
    twists = rng.normal(size=(40, 6)) * 10.0 ** rng.uniform(-12, 0, (40, 1))
    twists[0, 3:] = 0.0  # no rotation: the small-angle branch
    poses = se3_exp_many(twists)
    np.testing.assert_allclose(poses, np.stack([se3_exp(t) for t in twists]), rtol=0, atol=1e-15)
    logs = se3_log_many(poses)
    want = np.stack([se3_log(p) for p in poses])
    np.testing.assert_array_equal(logs[:, 3:], want[:, 3:])
    np.testing.assert_allclose(logs[:, :3], want[:, :3], rtol=0, atol=1e-15)
