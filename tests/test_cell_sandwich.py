"""The measurement covariance widened to its inliers' spread over the image's cells."""

from __future__ import annotations

import numpy as np
from test_pose_p3p import TRUE_POSE, correspondences, make_camera

from reloc_service.algorithms.pose.cell_sandwich import (
    FALSE_ALARM,
    SPREAD_LIMITS,
    cell_sandwich,
    grid_cells,
    simulated_limit,
    spread_limit,
    widened,
)
from reloc_service.algorithms.pose.intrinsics import CLUSTER_GRID
from reloc_service.algorithms.pose.pnp import PnPConf, solve_pnp_indexed
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


def test_spread_limit_is_the_largest_eigenvalues_quantile_and_falls_with_more_cells():
    assert spread_limit(3) > spread_limit(16) > spread_limit(64) > 1.0
    # Independent draws (another seed) exceed it at the false-alarm rate.
    draws = np.random.default_rng(6).standard_normal((20000, 15, 6))
    largest = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", draws, draws))[:, -1] / 15
    assert abs(np.mean(largest > spread_limit(16)) - FALSE_ALARM) < 0.004


def test_tabled_limits_are_the_simulated_ones():
    assert sorted(SPREAD_LIMITS) == list(range(3, 17))
    for cells in (3, 9, 16):
        assert spread_limit(cells) == simulated_limit(cells, FALSE_ALARM)
    assert spread_limit(40) == simulated_limit(40, FALSE_ALARM)


def test_sandwich_needs_three_cells():
    scores = np.ones((10, 6))
    assert cell_sandwich(np.eye(6), scores, np.zeros(10, np.int64)) is None
    assert cell_sandwich(np.eye(6), scores, np.arange(10) % 2) is None
    out = cell_sandwich(np.eye(6), scores, np.arange(10) % 3)
    assert out is not None and out[1] == 3
