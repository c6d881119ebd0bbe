"""algorithms/pose/intrinsics_marginal.py: a query that claims the map's calibration answers
with the calibration prior and the data's intrinsics estimate combined (their posterior),
calibrated where the prior holds; one that claims another camera with the marginal
covariance (:func:`.map_consistency.covariance_with_intrinsics`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats
from test_pose_intrinsics import POSE, ROOM, correspondences

from reloc_service.algorithms.pose.intrinsics_marginal import intrinsics_posterior
from reloc_service.algorithms.pose.map_consistency import covariance_with_intrinsics
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.algorithms.relocalizers.base import stated_covariance
from reloc_service.tools.eval import metrics


def _solved(camera, n: int, noise_px: float, rng: np.random.Generator, spread: float = 1.0):
    px, points = correspondences(camera, n, noise_px, rng, spread=spread)
    solved = solve_pnp_indexed(px, points, ROOM, PnPConf())
    assert solved is not None
    est = solved[0]
    check = est.intrinsics_test()
    assert est.covariance is not None and check is not None
    return est, check


def test_calibration_errors_from_the_prior_are_covered_as_stated():
    """Cameras whose focal is off by draws from the calibration prior (0.5 %): the position
    errors of the poses at the given camera look like draws from the stated covariance
    (cov scale between 0.67 and 1.5, at most one beyond 3 sigma in 50) under the marginal
    covariance a query claiming another camera answers with."""
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


def settled_estimate(est, check, *, map_calibration: bool):
    """``est`` as a pose finder and a relocalizer leave it: judged, and noted whether the
    query claims the map's calibration."""
    est.intrinsics = check
    est.covariance_given_intrinsics = covariance_with_intrinsics(est.covariance, check,
                                                                 trusted=True)
    est.covariance = covariance_with_intrinsics(est.covariance, check)
    est.query_camera_is_map_calibration = map_calibration
    return est


def test_the_map_calibration_is_trusted_within_its_prior_where_the_query_claims_it():
    """A query that claims the camera of the keyframes behind its pose answers with the
    prior and the data combined (``d C + B (S + m m^T) B^T``, no stale-calibration
    envelope); one that claims another camera with the marginal covariance."""
    rng = np.random.default_rng(3)
    est, check = _solved(ROOM, 200, 0.5, rng)
    own = check.dispersion * est.covariance
    mine = settled_estimate(*_solved(ROOM, 200, 0.5, np.random.default_rng(3)), map_calibration=True)
    other = settled_estimate(est, check, map_calibration=False)
    m, s = intrinsics_posterior(check.theta, check.covariance, check.prior.covariance)
    b = check.pose_shift
    np.testing.assert_allclose(stated_covariance(mine, 0.2),
                               own + b @ (s + np.outer(m, m)) @ b.T, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(stated_covariance(other, 0.2), other.covariance)
    # the posterior is tighter than both the prior and the data alone
    for bound in (check.prior.covariance, check.covariance):
        assert np.linalg.eigvalsh(bound - s).min() > 0


def test_the_posterior_is_calibrated_where_the_prior_holds():
    """Intrinsics errors drawn from the prior and estimated with noise ``V``: the error
    whitened by the posterior is chi-square with 2 degrees of freedom (mean 2), where the
    prior alone or the data alone overstate it."""
    rng = np.random.default_rng(0)
    prior = np.diag([0.005**2, 2.0**2])
    data = np.array([[0.004**2, 0.5 * 0.004 * 1.5], [0.5 * 0.004 * 1.5, 1.5**2]])
    truth = rng.multivariate_normal(np.zeros(2), prior, 4000)
    estimates = truth + rng.multivariate_normal(np.zeros(2), data, 4000)
    whitened = []
    for theta, theta_hat in zip(truth, estimates, strict=True):
        m, s = intrinsics_posterior(theta_hat, data, prior)
        whitened.append((theta - m) @ np.linalg.solve(s, theta - m))
    assert abs(np.mean(whitened) - 2.0) < 0.1
    assert np.mean([(t - h) @ np.linalg.solve(data, t - h)
                    for t, h in zip(truth, estimates, strict=True)]) == pytest.approx(2.0, abs=0.1)


def test_map_calibration_answers_are_covered_as_stated():
    """Cameras whose focal is off by draws from the calibration prior, the query claiming
    the map's calibration: the position errors look like draws from the stated covariance
    (cov scale between 0.67 and 1.5, at most two beyond 3 sigma in 50)."""
    rng = np.random.default_rng(1)
    lengths = []
    for _ in range(50):
        scale = 1.0 + rng.normal(0.0, PnPConf().focal_sigma_rel)
        true_camera = dataclasses.replace(ROOM, fx=ROOM.fx * scale, fy=ROOM.fy * scale)
        est, check = _solved(true_camera, 200, 1.0, rng)
        if not check.passed:
            continue
        stated = stated_covariance(settled_estimate(est, check, map_calibration=True), 0.2)
        lengths.append(metrics.translation_mahalanobis(est.world_from_cam, POSE, stated))
    assert len(lengths) >= 45
    scale = metrics.covariance_scale(lengths, [True] * len(lengths))
    assert 0.67 <= scale <= 1.5, scale
    assert np.count_nonzero(np.array(lengths) > 3.0) <= 2


def _exact_calibration_lengths(calibration: np.ndarray, seed: int) -> list[float]:
    """Mahalanobis lengths of 50 poses solved with the exact camera (keypoint noise 1 px,
    exact landmarks), the query claiming the map's calibration stated as ``calibration``."""
    rng = np.random.default_rng(seed)
    lengths = []
    for _ in range(50):
        est, check = _solved(ROOM, 200, 1.0, rng)
        if not check.passed:
            continue
        settled = settled_estimate(est, check, map_calibration=True)
        settled.calibration_covariance = calibration
        lengths.append(metrics.translation_mahalanobis(
            est.world_from_cam, POSE, stated_covariance(settled, 0.2)))
    assert len(lengths) >= 45
    return lengths


def test_an_exact_calibration_states_the_pose_at_the_given_camera_alone():
    """A map that states its calibration exact (``P = 0``): the answer's covariance is the
    pose's at the given intrinsics (``d C``), no calibration part and no other solution
    mixed in; a stated prior adds ``B (S + m m^T) B^T``, whatever the test allowed."""
    est, check = _solved(ROOM, 200, 0.5, np.random.default_rng(3))
    own = check.dispersion * est.covariance
    settled = settled_estimate(est, check, map_calibration=True)
    settled.calibration_covariance = np.zeros((2, 2))
    np.testing.assert_allclose(stated_covariance(settled, 0.2), own, rtol=1e-9, atol=1e-15)
    loose = np.diag([0.02**2, 4.0**2])
    settled.calibration_covariance = loose
    m, s = intrinsics_posterior(check.theta, check.covariance, loose)
    b = check.pose_shift
    np.testing.assert_allclose(stated_covariance(settled, 0.2),
                               own + b @ (s + np.outer(m, m)) @ b.T, rtol=1e-9, atol=1e-15)


def test_exact_calibration_answers_are_covered_as_stated():
    """Poses solved with the exact camera (exact truth): under the exact calibration the map
    states, the position errors look like draws from the stated covariance (cov scale
    between 0.67 and 1.5; beyond 3 sigma no more often than the binomial 99.9 % quantile of
    Gaussian errors' chi-square(3) tail allows); the routine calibration prior (0.5 % focal)
    stated instead widens the covariance beyond what the errors show."""
    exact = _exact_calibration_lengths(np.zeros((2, 2)), seed=5)
    scale = metrics.covariance_scale(exact, [True] * len(exact))
    assert 0.67 <= scale <= 1.5, scale
    tail = float(stats.chi2.sf(9.0, 3))
    assert np.count_nonzero(np.array(exact) > 3.0) <= stats.binom.ppf(0.999, len(exact), tail)
    routine = _exact_calibration_lengths(np.diag([0.005**2, 2.0**2]), seed=5)
    assert metrics.covariance_scale(routine, [True] * len(routine)) < scale


def test_the_gain_form_posterior_equals_the_information_form():
    """``m = P (P + V)^-1 theta_hat``, ``S = P - P (P + V)^-1 P`` equal the information
    form ``S = (P^-1 + V^-1)^-1``, ``m = S V^-1 theta_hat`` where both exist."""
    prior = np.diag([0.005**2, 2.0**2])
    data = np.array([[0.004**2, 0.5 * 0.004 * 1.5], [0.5 * 0.004 * 1.5, 1.5**2]])
    theta_hat = np.array([0.003, -1.0])
    m, s = intrinsics_posterior(theta_hat, data, prior)
    s_info = np.linalg.inv(np.linalg.inv(prior) + np.linalg.inv(data))
    np.testing.assert_allclose(s, s_info, rtol=1e-9)
    np.testing.assert_allclose(m, s_info @ np.linalg.solve(data, theta_hat), rtol=1e-9)
    m0, s0 = intrinsics_posterior(theta_hat, data, np.zeros((2, 2)))
    assert not m0.any() and not s0.any()
