"""The chance model of matches drawn from the prior's windows."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.pose.prior_windows import window_chance


def test_window_chance_is_the_inlier_disc_over_each_window_averaged_and_capped_at_one():
    t = 3.0
    disc = np.pi * t * t
    # A window 10x the inlier disc, one 4x, and one smaller than the disc (chance 1).
    areas = np.array([10 * disc, 4 * disc, 0.5 * disc])
    assert window_chance(t, areas) == pytest.approx((0.1 + 0.25 + 1.0) / 3)
    # Wider windows, a smaller chance of agreeing with the pose by accident.
    assert window_chance(t, 2 * areas[:2]) < window_chance(t, areas[:2])


def test_window_chance_is_zero_without_a_threshold_or_matches():
    assert window_chance(None, np.array([100.0])) == 0.0
    assert window_chance(2.0, np.zeros(0)) == 0.0
