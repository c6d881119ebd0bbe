"""The measurement covariance widened to its inliers' spread over the image's cells."""

from __future__ import annotations

import numpy as np
import pytest
from test_pose_p3p import TRUE_POSE, correspondences, make_camera

from reloc_service.algorithms.pose.cell_sandwich import (
    FALSE_ALARM,
    SPREAD_LIMITS,
    cell_sandwich,
    effective_cells,
    grid_cells,
    simulated_limit,
    spread_limit,
    tracy_widom_limit,
    widened,
)
from reloc_service.algorithms.pose.intrinsics import CLUSTER_GRID
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.core.geometry import invert, se3_log


def _stated(est: object) -> np.ndarray:
    sandwich = est.measurement_sandwich()  # type: ignore[attr-defined]
    assert sandwich is not None
    return widened(est.covariance, *sandwich)  # type: ignore[attr-defined]


def _mahalanobis(est: object, covariance: np.ndarray) -> float:
    twist = se3_log(invert(TRUE_POSE) @ est.world_from_cam)  # type: ignore[attr-defined]
    return float(twist @ np.linalg.solve(covariance, twist))


def test_honest_residuals_are_rarely_widened():
    # Independent 1 px noise: the model covariance holds, and the widening fires at about
    # its false-alarm rate (binomial bound: 60 draws at 1 % exceed 4 with probability 0.3 %).
    rng = np.random.default_rng(3)
    camera = make_camera("radtan")
    clean, points = correspondences(camera, TRUE_POSE, 200, rng)
    fired = 0
    for _ in range(60):
        est, _ = solve_pnp_indexed(clean + rng.normal(0.0, 1.0, clean.shape), points, camera,
                                   PnPConf(min_sigma_px=0.0))
        fired += not np.allclose(_stated(est), est.covariance)
    assert fired <= 4


def test_coherent_cell_shifts_widen_to_cover_the_error():
    # Each cell's keypoints shifted together (blur, a landmark region off): the residuals'
    # scale stays that of the noise, the pose error does not shrink with the inliers, and
    # only the cells' spread shows it.
    rng = np.random.default_rng(4)
    camera = make_camera("pinhole")
    clean, points = correspondences(camera, TRUE_POSE, 400, rng)
    cells = grid_cells(clean, camera.size, CLUSTER_GRID)
    model, stated = [], []
    for _ in range(40):
        shift = rng.normal(0.0, 1.0, (CLUSTER_GRID**2, 2))[cells]
        est, _ = solve_pnp_indexed(clean + shift + rng.normal(0.0, 0.3, clean.shape), points,
                                   camera, PnPConf(min_sigma_px=0.0))
        model.append(_mahalanobis(est, est.covariance))
        stated.append(_mahalanobis(est, _stated(est)))
    # chi-square with 6 degrees of freedom has median 5.35: the model is far too confident;
    # the widened covariance, lifted only where 16 cells' spread is beyond chance, is
    # less than half as far off (what the cells cannot show, they do not cover).
    assert np.median(model) > 20.0
    assert np.median(stated) < 0.5 * np.median(model)


def test_widening_never_narrows_and_keeps_the_model_where_the_spread_is_small():
    rng = np.random.default_rng(5)
    a = rng.normal(size=(6, 6))
    covariance = a @ a.T + 6 * np.eye(6)
    b = rng.normal(size=(6, 6))
    small = 0.5 * covariance
    assert np.allclose(widened(covariance, small, 16), covariance)
    large = covariance + 50.0 * np.outer(b[0], b[0])
    out = widened(covariance, large, 16)
    assert np.linalg.eigvalsh(out - covariance).min() > -1e-9
    assert float(b[0] @ out @ b[0]) > 10.0 * float(b[0] @ covariance @ b[0])


def test_an_unknown_covariance_is_left_unknown():
    """A singular fit states an infinite covariance (every direction unknown): widening
    returns it as it is instead of failing in the eigen-solver."""
    rng = np.random.default_rng(6)
    a = rng.normal(size=(6, 6))
    sandwich = a @ a.T + 6 * np.eye(6)
    unknown = np.full((6, 6), np.inf)
    assert np.all(np.isinf(widened(unknown, sandwich, 16)))


def test_spread_limit_is_the_largest_eigenvalues_quantile_and_falls_with_more_cells():
    assert spread_limit(3) > spread_limit(16) > spread_limit(64) > 1.0
    # Independent draws (another seed) exceed it at the false-alarm rate.
    draws = np.random.default_rng(6).standard_normal((20000, 15, 6))
    largest = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", draws, draws))[:, -1] / 15
    assert abs(np.mean(largest > spread_limit(16)) - FALSE_ALARM) < 0.004


def test_tabled_limits_are_the_simulated_ones():
    assert sorted(SPREAD_LIMITS) == list(range(3, 17))
    # Equal to rounding: the simulation's eigenvalues differ in the last bits between BLAS
    # builds, a quantile of them by an ulp.
    for cells in (3, 9, 16):
        assert spread_limit(cells) == pytest.approx(simulated_limit(cells, FALSE_ALARM),
                                                    rel=1e-12)
    assert spread_limit(40) == tracy_widom_limit(40)


@pytest.mark.parametrize("cells", [8, 16, 30, 60, 120])
def test_tracy_widom_limit_is_within_one_percent_of_the_simulated(cells):
    assert tracy_widom_limit(cells) == pytest.approx(simulated_limit(cells, FALSE_ALARM),
                                                     rel=0.01)


def test_sandwich_needs_three_cells():
    scores = np.ones((10, 6))
    assert cell_sandwich(np.eye(6), scores, np.zeros(10, np.int64)) is None
    assert cell_sandwich(np.eye(6), scores, np.arange(10) % 2) is None
    out = cell_sandwich(np.eye(6), scores, np.arange(10) % 3)
    assert out is not None and out[1] == 3


def _point_widened(est: object) -> np.ndarray:
    sandwich = est.point_sandwich()  # type: ignore[attr-defined]
    # as many effective cells as equal cells would weigh, fewer than the inliers
    assert sandwich is not None and 3 <= sandwich[1] < est.inliers  # type: ignore[attr-defined]
    return widened(est.covariance, *sandwich)  # type: ignore[attr-defined]


POINT_CONF = PnPConf(min_sigma_px=0.0, stated_point_sandwich=True)


def test_point_sandwich_is_there_by_default_and_only_then():
    rng = np.random.default_rng(7)
    camera = make_camera("radtan")
    clean, points = correspondences(camera, TRUE_POSE, 100, rng)
    noisy = clean + rng.normal(0.0, 1.0, clean.shape)
    off = PnPConf(min_sigma_px=0.0, stated_point_sandwich=False)
    est, _ = solve_pnp_indexed(noisy, points, camera, off)
    assert est.point_sandwich is None
    est, _ = solve_pnp_indexed(noisy, points, camera, PnPConf(min_sigma_px=0.0))
    assert est.point_sandwich is not None


def test_honest_residuals_are_rarely_widened_point_by_point():
    # Independent isotropic 1 px noise: one residual variance for all inliers holds, and the
    # point-by-point widening fires at about its 1 % false-alarm rate.
    rng = np.random.default_rng(8)
    camera = make_camera("radtan")
    clean, points = correspondences(camera, TRUE_POSE, 150, rng)
    fired = 0
    for _ in range(60):
        est, _ = solve_pnp_indexed(clean + rng.normal(0.0, 1.0, clean.shape), points, camera,
                                   POINT_CONF)
        fired += not np.allclose(_point_widened(est), est.covariance)
    assert fired <= 4


def test_noise_growing_with_leverage_along_one_direction_is_covered():
    # Keypoint noise along x only (a horizontal blur), growing towards the image's sides
    # where the points weigh most on the pose: one residual variance for all inliers
    # under-states the pose's spread; the points' own spread shows it.
    rng = np.random.default_rng(9)
    camera = make_camera("pinhole")
    clean, points = correspondences(camera, TRUE_POSE, 300, rng)
    lever = np.abs(clean[:, 0] - camera.width / 2) / (camera.width / 2)
    model, stated = [], []
    for _ in range(40):
        noise = np.zeros_like(clean)
        noise[:, 0] = rng.normal(0.0, 0.2 + 3.0 * lever**2)
        est, _ = solve_pnp_indexed(clean + noise, points, camera, POINT_CONF)
        model.append(_mahalanobis(est, est.covariance))
        stated.append(_mahalanobis(est, _point_widened(est)))
    # chi-square with 6 degrees of freedom has median 5.35
    assert np.median(model) > 8.0
    assert np.median(stated) < 0.75 * np.median(model)


def test_equal_points_count_as_equal_cells_and_a_dominant_point_as_fewer():
    rng = np.random.default_rng(10)
    a = rng.normal(size=(6, 6))
    normal = a @ a.T + 6 * np.eye(6)
    assert effective_cells(np.linalg.inv(normal), np.repeat(normal[None] / 20, 20, 0)) == 20
    skewed = np.repeat(normal[None] / 40, 20, 0)
    skewed[0] += normal / 2                                 # one point holds half the weight
    assert effective_cells(np.linalg.inv(normal), skewed) < 10
