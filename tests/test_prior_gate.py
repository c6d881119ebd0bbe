"""The prior's gate a tracked pose must meet: the twist from the prior to the answer,
Mahalanobis under the sum of both covariances, within chi-square of 6 degrees of freedom."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.pose.prior_gate import within_prior
from reloc_service.core import distributions as stats
from reloc_service.core.geometry import pose_covariance_from_sigmas, se3_exp

PRIOR = pose_covariance_from_sigmas(0.05, np.deg2rad(2.0))


def _pose(rng):
    return se3_exp(np.concatenate([rng.normal(0, 1.0, 3), rng.normal(0, 0.5, 3)]))


@pytest.mark.parametrize("axis", range(6))
def test_the_gate_is_the_chi_square_quantile_along_each_axis(axis):
    """An answer moved ``k`` sigmas of the summed covariance along one twist axis lies
    inside the gate exactly while ``k^2`` stays within ``chi2_6(p)``."""
    prior_pose = _pose(np.random.default_rng(axis))
    answer_cov = 0.25 * PRIOR
    sigma = float(np.sqrt(PRIOR[axis, axis] + answer_cov[axis, axis]))
    limit = float(np.sqrt(stats.chi2.ppf(0.999, 6)))
    for k, inside in ((0.0, True), (0.97 * limit, True), (1.03 * limit, False)):
        xi = np.zeros(6)
        xi[axis] = k * sigma
        answer = prior_pose @ se3_exp(xi)
        assert within_prior(answer, answer_cov, prior_pose, PRIOR, 0.999) is inside, (k, axis)


def test_a_pose_two_metres_off_a_sharp_prior_is_outside_and_no_covariance_reads_the_prior():
    prior_pose = _pose(np.random.default_rng(7))
    far = prior_pose.copy()
    far[:3, 3] += [2.0, 0.0, 0.0]
    assert not within_prior(far, 0.01 * PRIOR, prior_pose, PRIOR, 0.999)
    # Without a stated covariance the prior's alone makes the gate.
    near = prior_pose @ se3_exp(np.array([0.05, 0, 0, 0, 0, 0]))
    assert within_prior(near, None, prior_pose, PRIOR, 0.999)
    assert not within_prior(prior_pose @ se3_exp(np.array([0.3, 0, 0, 0, 0, 0])), None,
                            prior_pose, PRIOR, 0.999)
