"""The keypoint noise a pose's inliers show once the inlier gate's truncation is undone."""

from __future__ import annotations

import numpy as np
import pytest
from test_pose_p3p import TRUE_POSE, correspondences, make_camera

from reloc_service.algorithms.pose.gate_truncation import (
    kept_share,
    truncation_factor,
    untruncated_variance,
)
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.core.geometry import invert, se3_log


def _gated(rng: np.random.Generator, sigmas: np.ndarray, gate: float) -> np.ndarray:
    """(M,) the kept ones of ``sigmas`` and their residuals: 2-D Gaussian noise of each
    sigma per axis, kept within radius ``gate`` -> (kept index, squared length)."""
    r = rng.normal(0.0, 1.0, (len(sigmas), 2)) * sigmas[:, None]
    sq = (r**2).sum(axis=1)
    keep = sq < gate**2
    return np.flatnonzero(keep), sq[keep]


def test_kept_share_matches_a_truncated_sample():
    rng = np.random.default_rng(0)
    sigma, gate = 2.5, 5.0
    _, sq = _gated(rng, np.full(200_000, sigma), gate)
    share = sq.mean() / (2 * sigma**2)
    assert kept_share(np.array([gate**2 / (2 * sigma**2)]))[0] == pytest.approx(share, rel=0.01)
    assert kept_share(np.array([50.0]))[0] == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("sigma", [2.0, 3.0])
def test_untruncated_variance_recovers_the_noise_the_gate_cut(sigma):
    # Level-0 keypoints and level-1 ones (half the weight's root: twice the noise).
    rng = np.random.default_rng(1)
    weights = np.where(np.arange(3000) % 3 == 0, 0.25, 1.0)
    kept, sq = _gated(rng, sigma / np.sqrt(weights), 5.0)
    weighted_sq = float((weights[kept] * sq).sum())
    plain = weighted_sq / (2 * len(kept) - 6)
    estimate = untruncated_variance(weights[kept], weighted_sq, 5.0)
    assert plain < 0.85 * sigma**2                       # the residuals understate the noise
    assert estimate == pytest.approx(sigma**2, rel=0.06)


def test_no_truncation_no_change_and_bounded_where_unknown():
    rng = np.random.default_rng(2)
    kept, sq = _gated(rng, np.full(500, 0.5), 5.0)
    assert truncation_factor(np.ones(len(kept)), float(sq.sum()), 5.0) == pytest.approx(
        1.0, abs=1e-6)
    # residuals spread evenly over the gate's disk: as wide as it lets them be, no bound
    # from the data; the median inlier's gate at 1 sigma is stated
    even = 25.0 * rng.uniform(0, 1, 400)
    assert untruncated_variance(np.ones(400), float(even.sum()), 5.0) == pytest.approx(25.0)
    assert np.isnan(untruncated_variance(np.ones(3), 1.0, 5.0))


def test_stated_covariance_holds_blur_sized_noise_only_with_the_correction():
    # 3 px per axis, a 5 px gate: the plain covariance puts far more than 2.9 % of the
    # position errors beyond 3 sigma, the widened one much fewer.
    rng = np.random.default_rng(5)
    camera = make_camera("radtan")
    clean, points = correspondences(camera, TRUE_POSE, 80, rng)
    conf = PnPConf(min_sigma_px=0.0, intrinsics_false_refusal=0.0,
                   stated_point_sandwich=False, stated_cell_sandwich=False)
    plain, widened = [], []
    for _ in range(150):
        est, _ = solve_pnp_indexed(clean + rng.normal(0.0, 3.0, clean.shape), points, camera,
                                   conf)
        twist = se3_log(invert(TRUE_POSE) @ est.world_from_cam)
        extra = est.gate_truncation()
        assert extra is not None and np.all(np.linalg.eigvalsh(extra) >= -1e-15)
        plain.append(twist @ np.linalg.solve(est.covariance, twist))
        widened.append(twist @ np.linalg.solve(est.covariance + extra, twist))
    # chi-square(6) beyond 16.81 is 1 %
    assert np.mean(np.array(plain) > 16.81) > 0.05
    assert np.mean(np.array(widened) > 16.81) < np.mean(np.array(plain) > 16.81) / 2


def test_off_and_small_noise_add_nothing():
    rng = np.random.default_rng(6)
    camera = make_camera("radtan")
    clean, points = correspondences(camera, TRUE_POSE, 80, rng)
    noisy = clean + rng.normal(0.0, 0.7, clean.shape)
    est, _ = solve_pnp_indexed(noisy, points, camera, PnPConf(stated_gate_truncation=False))
    assert est.gate_truncation is None
    est, _ = solve_pnp_indexed(noisy, points, camera, PnPConf())
    assert est.gate_truncation is not None
    extra = est.gate_truncation()
    # 0.7 px against a 5 px gate: the gate cut a share e^-25 of the noise, nothing to state
    assert extra is None or np.abs(extra).max() < 1e-6 * np.abs(est.covariance).max()
