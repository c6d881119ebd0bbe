"""The grid's windows are the KD-tree's, element for element."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from reloc_service.algorithms.pose import keypoint_grid
from reloc_service.algorithms.pose.keypoint_grid import window_neighbours


def _tree_windows(keypoints_px, px, k, radius_px):
    _, near = cKDTree(keypoints_px).query(px, k=k, distance_upper_bound=radius_px)
    return np.asarray(near).reshape(len(px), k)


def _keypoints(rng, n, kind):
    """ORB-like (integer pixels of pyramid levels scaled back, so repeated positions), integer
    or continuous keypoints in a 640 x 480 image."""
    if kind == "continuous":
        return rng.uniform(0, 640, (n, 2)) * [1.0, 0.75]
    kp = rng.integers(0, 480, (n, 2)).astype(np.float64)
    if kind == "levels":
        kp *= 1.2 ** rng.integers(0, 8, (n, 1))
        kp[: n // 5] = kp[n // 5: 2 * (n // 5)]          # the same position twice
    return kp


@pytest.mark.parametrize("kind", ["continuous", "integer", "levels"])
@pytest.mark.parametrize("k", [8, 1, 3])
@pytest.mark.parametrize("radius_px", [10.0, 2.0, 4.5, 37.25])
def test_windows_are_the_kd_trees(kind, k, radius_px):
    """Projections anywhere (outside the keypoints' extent too), next to keypoints, exactly on
    them and exactly one radius away (the tree's boundary), against repeated keypoints: the
    same indices in the same order, empty slots K, as ``cKDTree.query``."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(k * 100 + int(radius_px))
    kp = _keypoints(rng, 500, kind)
    on = kp[rng.integers(0, len(kp), 300)]
    px = np.concatenate([
        rng.uniform(-50, 700, (3000, 2)),
        on + rng.uniform(-radius_px, radius_px, on.shape),
        on, on + [radius_px, 0.0], on - [0.0, radius_px],
        on + rng.integers(-3, 4, on.shape) * 0.5])
    got = window_neighbours(kp, px, k, radius_px, cKDTree(kp))
    assert got.dtype == np.int64
    assert np.array_equal(got, _tree_windows(kp, px, k, radius_px))


def test_the_grid_answers_most_landmarks_itself_and_the_tree_only_the_doubtful(monkeypatch):
    """Only landmarks with tied (or boundary) distances are asked of the tree: the grid's
    answers are its own elsewhere (a test of the fast path, not of the fallback)."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(5)
    kp = _keypoints(rng, 500, "levels")
    px = np.concatenate([rng.uniform(0, 640, (2000, 2)), kp[:100]])
    asked = []

    class CountingTree(cKDTree):
        def query(self, x, *args, **kwargs):
            asked.append(len(x))
            return super().query(x, *args, **kwargs)

    got = window_neighbours(kp, px, 8, 10.0, CountingTree(kp))
    assert np.array_equal(got, _tree_windows(kp, px, 8, 10.0))
    assert asked and 0 < sum(asked) < len(px) // 5   # near the repeated positions only


def test_without_numba_the_tree_answers(monkeypatch):
    rng = np.random.default_rng(2)
    kp, px = rng.uniform(0, 100, (40, 2)), rng.uniform(0, 100, (300, 2))
    monkeypatch.setattr(keypoint_grid, "compiled", lambda: None)
    got = window_neighbours(kp, px, 8, 6.0, lambda: cKDTree(kp))
    assert np.array_equal(got, _tree_windows(kp, px, 8, 6.0))


def test_empty_inputs_and_a_tiny_radius_fall_back():
    pytest.importorskip("numba")
    kp = np.array([[0.0, 0.0], [600.0, 400.0]])
    px = np.array([[0.0, 0.0], [600.0, 400.0001], [5.0, 5.0]])
    assert np.array_equal(window_neighbours(kp, px, 2, 1e-5, cKDTree(kp)),
                          _tree_windows(kp, px, 2, 1e-5))
    assert window_neighbours(kp, np.zeros((0, 2)), 2, 3.0, cKDTree(kp)).shape == (0, 2)
