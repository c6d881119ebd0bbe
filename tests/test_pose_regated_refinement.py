"""Re-gated refinement from a pose with a covariance: gates from the predicted residuals,
rounds until the kept set repeats, the P3P solve's estimate at the end."""

from __future__ import annotations

import numpy as np

from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.algorithms.pose.regated_refinement import covariance_gated, refine_from
from reloc_service.core.cameras import camera_from_dict
from reloc_service.core.geometry import look_at, pose_error, transform_points

GATE_99 = 9.2103  # chi2_2(0.99)
TRUE_POSE = look_at([0.4, -0.3, -4.0], [0.1, 0.2, 0.0], up=[0, -1, 0])
CAMERA = camera_from_dict({"model": "pinhole", "width": 640, "height": 480, "fx": 420.0,
                           "fy": 415.0, "cx": 322.5, "cy": 237.5})


def _pixels_and_points(rng, n, x_range):
    px = rng.uniform([x_range[0], 0], [x_range[1], CAMERA.height - 1], (n, 2))
    bearings = CAMERA.unproject(px)
    points_cam = bearings / bearings[:, 2:] * rng.uniform(1.5, 6.0, n)[:, None]
    return CAMERA.project(points_cam), transform_points(TRUE_POSE, points_cam)


def test_the_gate_is_the_residual_covariance_chi_square():
    jac = np.zeros((3, 2, 6))
    jac[:, 0, 0] = 1.0  # the first twist component moves x by one pixel per unit
    residuals = np.array([[3.0, 0.0], [3.1, 0.0], [4.0, 0.0]])
    noise = np.ones(3)
    assert list(covariance_gated(residuals, jac, noise, np.zeros((6, 6)), GATE_99)) == [0]
    # a unit variance of the pose along that component doubles x's variance: 4^2 / 2 = 8
    cov = np.zeros((6, 6))
    cov[0, 0] = 1.0
    assert list(covariance_gated(residuals, jac, noise, cov, GATE_99)) == [0, 1, 2]
    residuals[2] = np.nan
    assert list(covariance_gated(residuals, jac, noise, cov, GATE_99)) == [0, 1]


def test_a_pose_solved_on_one_side_reaches_the_whole_image_and_drops_outliers():
    rng = np.random.default_rng(0)
    conf = PnPConf()
    seed_px, seed_pts = _pixels_and_points(rng, 25, (0, 120))
    rest_px, rest_pts = _pixels_and_points(rng, 200, (120, CAMERA.width - 1))
    bad_px = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (40, 2))
    _, bad_pts = _pixels_and_points(rng, 40, (0, CAMERA.width - 1))
    px = np.concatenate([seed_px, rest_px, bad_px])
    px[:225] += rng.normal(0.0, 1.0, (225, 2))
    pts = np.concatenate([seed_pts, rest_pts, bad_pts])
    solved = solve_pnp_indexed(px[:25], pts[:25], CAMERA, conf)
    assert solved is not None
    seed = solved[0]
    refined = refine_from(seed, px, pts, CAMERA, conf, None, GATE_99)
    assert refined is not None
    est, inliers = refined
    assert np.count_nonzero(inliers < 225) >= 215   # the right ones, a 5 px gate at 1 px noise
    assert np.count_nonzero(inliers >= 225) <= 1     # a random pixel may land in a gate
    assert est.inliers == len(inliers) and est.covariance is not None
    t_seed, _ = pose_error(seed.world_from_cam, TRUE_POSE)
    t_refined, r_refined = pose_error(est.world_from_cam, TRUE_POSE)
    assert t_refined < t_seed and t_refined < 0.01 and np.degrees(r_refined) < 0.2


def test_no_refinement_without_a_finite_covariance():
    rng = np.random.default_rng(1)
    px, pts = _pixels_and_points(rng, 50, (0, CAMERA.width - 1))
    solved = solve_pnp_indexed(px, pts, CAMERA, PnPConf())
    assert solved is not None
    est = solved[0]
    est.covariance = np.full((6, 6), np.inf)
    assert refine_from(est, px, pts, CAMERA, PnPConf(), None, GATE_99) is None
