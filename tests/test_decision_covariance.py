"""algorithms/pose/decision_covariance.py: the verification weighs a pose by its marginal
covariance (the intrinsics free, the calibration prior not trusted), whatever covariance the
answer states; a query claiming the map's calibration answers with the tighter posterior but
is judged as one claiming another camera would be."""

from __future__ import annotations

import numpy as np
import pytest
from test_intrinsics_marginal import _solved, settled_estimate
from test_pose_intrinsics import ROOM

from reloc_service.algorithms.pose.base import total_covariance
from reloc_service.algorithms.pose.decision_covariance import decision_covariance
from reloc_service.algorithms.relocalizers.base import (
    VerifyConf,
    gate_widened,
    intrinsics_unchecked,
    point_widened,
    position_sigma_m,
    result_from_estimate,
    stated_covariance,
    verify,
)


def _pair(seed: int, n: int = 60, noise_px: float = 1.0):
    """One solved pose settled twice: claiming the map's calibration, and another camera."""
    mine = settled_estimate(*_solved(ROOM, n, noise_px, np.random.default_rng(seed)),
                            map_calibration=True)
    other = settled_estimate(*_solved(ROOM, n, noise_px, np.random.default_rng(seed)),
                              map_calibration=False)
    return mine, other


def test_the_decision_covariance_is_the_marginal_whatever_the_answer_states():
    """The posterior an answer claiming the map's calibration states is several times
    tighter than the marginal covariance; the decision's is the marginal one for both
    claims, with the keyframe poses' errors added."""
    mine, other = _pair(1)
    mine.map_covariance = other.map_covariance = np.diag([1e-4] * 3 + [1e-6] * 3)
    for est in (mine, other):
        np.testing.assert_array_equal(decision_covariance(est, intrinsics_unchecked=False),
                                      total_covariance(est))
    assert position_sigma_m(stated_covariance(mine, 1.0)) < 0.5 * position_sigma_m(
        decision_covariance(mine, intrinsics_unchecked=False))
    # another camera's answer states the marginal (widened to its inliers' own spread and to
    # the noise the inlier gate cut)
    np.testing.assert_array_equal(
        stated_covariance(other, 1.0),
        total_covariance(other, gate_widened(other, point_widened(other, other.covariance))))
    unchecked = decision_covariance(mine, intrinsics_unchecked=True)
    assert mine.covariance_given_intrinsics is not None
    np.testing.assert_array_equal(unchecked,
                                  mine.covariance_given_intrinsics + mine.map_covariance)


def test_the_position_gate_reads_the_decision_covariance_not_the_stated_one():
    """A bound on the position sigma between the stated posterior's and the marginal's: the
    pose is refused as too uncertain whether or not the query claims the map's calibration
    (a gate reading the stated covariance would pass the map-calibration claim), and the
    answer given under a looser bound states the posterior."""
    mine, other = _pair(1)
    stated = position_sigma_m(stated_covariance(mine, 1.0))
    judged = position_sigma_m(decision_covariance(mine, intrinsics_unchecked=False))
    bound = 0.97 * judged   # above what a view that cannot check the intrinsics would give
    assert stated < bound < judged
    assert not intrinsics_unchecked(mine, bound)
    for est in (mine, other):
        ok, reason, _ = verify(est, VerifyConf(max_position_sigma_m=bound))
        assert not ok and "position too uncertain" in reason
    loose = VerifyConf(max_position_sigma_m=2.0 * judged)
    assert verify(mine, loose) == verify(other, loose)
    answer = result_from_estimate(mine, loose, method="sbi+p3p", map_version=1, timings={})
    assert answer.ok and answer.covariance is not None
    assert position_sigma_m(answer.covariance) == pytest.approx(stated)
