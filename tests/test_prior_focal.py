"""The focal starts of the intrinsics test that a pose prior leaves open: a start is kept
while its basin (half a step of the series of focal scales) meets the focal errors whose
shift along the optical axis the prior's gate admits."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.pose.intrinsics import FOCAL_STARTS
from reloc_service.algorithms.pose.prior_focal import (
    axis_variance,
    focal_reach,
    focal_starts_within,
)
from reloc_service.core.geometry import pose_covariance_from_sigmas


def test_reach_is_the_gate_along_the_axis_over_the_depth():
    # 5 cm along the axis, gate of 4 sigma, scene 2 m away: 20 cm of shift = 10 % of focal.
    assert focal_reach(0.05**2, 2.0, 16.0) == pytest.approx(0.1)
    assert focal_reach(0.05**2, 0.0, 16.0) == np.inf
    assert focal_reach(0.05**2, float("nan"), 16.0) == np.inf


@pytest.mark.parametrize(("reach", "kept"), [
    (0.0, ()),                       # the given focal's basin (within 7.2 %) is enough
    (0.05, ()),
    (0.10, (1 / 1.15, 1.15)),        # 1.15's basin starts at 1.15 / sqrt(1.15) = 1.072
    (0.20, (1.15**-2, 1 / 1.15, 1.15)),   # 1.3225's starts at 1.233 > 1.2; 0.756's ends at 0.81
    (np.inf, FOCAL_STARTS),
])
def test_starts_kept_are_those_whose_basin_meets_the_admissible_focals(reach, kept):
    assert focal_starts_within(reach) == pytest.approx(tuple(sorted(kept, key=FOCAL_STARTS.index)))


def test_every_start_is_kept_once_the_reach_covers_the_series():
    assert focal_starts_within(0.6) == FOCAL_STARTS


def test_axis_variance_adds_the_answers_own():
    prior = pose_covariance_from_sigmas(0.05, np.deg2rad(2.0))
    own = np.diag([1e-4, 1e-4, 4e-4, 1e-6, 1e-6, 1e-6])
    assert axis_variance(prior, None) == pytest.approx(0.05**2)
    assert axis_variance(prior, own) == pytest.approx(0.05**2 + 4e-4)
