"""algorithms/pose/intrinsics_marginal.py: what the intrinsics add to a pose's covariance: the
data's estimate and its covariance (the calibration prior not added to them), the solutions
the data cannot exclude other than the tested one, and the envelope of what the test misses
as a floor rather than a further sum."""

from __future__ import annotations

import dataclasses

import numpy as np
from test_pose_intrinsics import POSE, ROOM, correspondences

from reloc_service.algorithms.pose.cluster_covariance import at_least
from reloc_service.algorithms.pose.intrinsics_marginal import (
    farthest_other_offset,
    intrinsics_marginal_covariance,
)
from reloc_service.algorithms.pose.intrinsics_power import undetected_covariance
from reloc_service.algorithms.pose.map_consistency import covariance_with_intrinsics
from reloc_service.algorithms.pose.pnp import PnPConf, solve_pnp_indexed
from reloc_service.tools.eval import metrics


def _solved(camera, n: int, noise_px: float, rng: np.random.Generator, spread: float = 1.0):
    px, points = correspondences(camera, n, noise_px, rng, spread=spread)
    solved = solve_pnp_indexed(px, points, ROOM, PnPConf())
    assert solved is not None
    est = solved[0]
    check = est.intrinsics_test()
    assert est.covariance is not None and check is not None
    return est, check


def test_the_larger_of_the_expected_error_and_the_envelope():
    """``d C + B (theta theta^T + V) B^T`` (no calibration prior added), at least the
    envelope ``d C + B k W B^T``: the covariance the relocalizers state."""
    est, check = _solved(ROOM, 200, 0.5, np.random.default_rng(3))
    assert check.passed and not farthest_other_offset(check).any()
    b, own = check.pose_shift, check.dispersion * est.covariance
    expected = own + b @ (check.covariance + np.outer(check.theta, check.theta)) @ b.T
    envelope = own + b @ undetected_covariance(check) @ b.T
    stated = covariance_with_intrinsics(est.covariance, check)
    np.testing.assert_allclose(stated, at_least(expected, envelope), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(stated, intrinsics_marginal_covariance(est.covariance, check))
    # a floor, not a sum: smaller than the two added, larger than either
    assert np.linalg.eigvalsh(expected + envelope - own - stated).min() > -1e-15
    assert np.trace((expected + envelope - own - stated)[:3, :3]) > 0
    for part in (expected, envelope):
        assert np.linalg.eigvalsh(stated - part).min() > -1e-12 * np.abs(stated).max()


def test_the_tested_solution_is_not_its_own_alternative():
    """The farthest solution the data cannot exclude adds its offset only when it is not
    the tested one, whose offset ``B theta_hat`` is in the covariance already."""
    est, check = _solved(ROOM, 30, 3.0, np.random.default_rng(5), spread=0.4)
    tested = check.solution
    alone = dataclasses.replace(check, solutions=(tested,))
    assert not farthest_other_offset(alone).any()
    assert np.linalg.norm(alone.unexcluded_twist) > 0
    far = farthest_other_offset(check)
    assert np.abs(far - tested.twist).max() >= 1e-3 or not far.any()


def test_calibration_errors_from_the_prior_are_covered_as_stated():
    """Cameras whose focal is off by draws from the calibration prior (0.5 %): the position
    errors of the poses at the given camera look like draws from the stated covariance
    (cov scale between 0.67 and 1.5, at most one beyond 3 sigma in 50): what the floor and
    the dropped sums leave is not too confident where the calibration is as good as its
    prior says."""
    rng = np.random.default_rng(0)
    lengths = []
    for _ in range(50):
        scale = 1.0 + rng.normal(0.0, PnPConf().focal_sigma_rel)
        true_camera = dataclasses.replace(ROOM, fx=ROOM.fx * scale, fy=ROOM.fy * scale)
        est, check = _solved(true_camera, 200, 1.0, rng)
        if not check.passed:
            continue
        stated = covariance_with_intrinsics(est.covariance, check)
        lengths.append(metrics.translation_mahalanobis(est.world_from_cam, POSE, stated))
    assert len(lengths) >= 45
    scale = metrics.covariance_scale(lengths, [True] * len(lengths))
    assert 0.67 <= scale <= 1.5, scale
    assert np.count_nonzero(np.array(lengths) > 3.0) <= 1
