"""Guided matching (search by projection): windows around projected landmarks, descriptor
tests inside them, and the P3P pose finder growing a weak first pose with it."""

import numpy as np
import pytest

from reloc_service.algorithms.pose.guided import GuidedConf, background_distance, search_by_projection
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.frame import Features
from reloc_service.core.geometry import look_at, se3_exp, transform_points

CAMERA = PinholeCamera(640, 480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
WORLD_FROM_CAM = look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], up=[0, -1, 0])


def _scene(n: int = 300, seed: int = 0):
    """Landmarks in front of the camera, SIFT-like descriptors, and query keypoints at their
    exact projections carrying the same descriptors with a little noise."""
    rng = np.random.default_rng(seed)
    px = rng.uniform([20, 20], [620, 460], (n, 2))
    bearings = CAMERA.unproject(px)
    points_cam = bearings / bearings[:, 2:] * rng.uniform(2.0, 5.0, n)[:, None]
    points_world = transform_points(WORLD_FROM_CAM, points_cam)
    desc = rng.integers(0, 256, (n, 128)).astype(np.float32)
    query_desc = np.clip(desc + rng.normal(0, 8, desc.shape), 0, 255).astype(np.float32)
    return Features.create("sift", px, query_desc), desc, points_world


def test_finds_landmarks_near_their_projection_under_a_slightly_wrong_pose():
    feats, desc, points = _scene()
    off = WORLD_FROM_CAM @ se3_exp([0.01, -0.01, 0.0, 0.0, 0.002, 0.0])   # ~1-4 px off
    q, rows = search_by_projection(feats, CAMERA, off, desc, points, 10.0, GuidedConf())
    assert len(q) > 0.95 * len(feats)
    assert np.array_equal(q, rows)                 # keypoint i is the projection of landmark i
    assert len(np.unique(q)) == len(q) and len(np.unique(rows)) == len(rows)


def test_windows_keep_far_landmarks_out_and_foreign_descriptors_fail():
    feats, desc, points = _scene()
    far = WORLD_FROM_CAM @ se3_exp([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])        # ~50 px off
    q, _ = search_by_projection(feats, CAMERA, far, desc, points, 10.0, GuidedConf())
    assert len(q) < 0.1 * len(feats)
    foreign = np.random.default_rng(9).integers(0, 256, desc.shape).astype(np.float32)
    q, _ = search_by_projection(feats, CAMERA, WORLD_FROM_CAM, foreign, points, 10.0,
                                GuidedConf())
    assert len(q) < 0.05 * len(feats)


def test_background_distance_is_a_low_quantile_of_unrelated_pairs():
    feats, desc, _ = _scene()
    limit = background_distance(feats.descriptors, desc, 0.01)
    matched = np.linalg.norm(feats.descriptors - desc, axis=1)
    assert np.median(matched) < limit
    assert background_distance(feats.descriptors[:0], desc, 0.01) == 0.0


def test_window_distances_of_binary_descriptors_are_hamming():
    from reloc_service.algorithms.pose.guided import _window_distances

    rng = np.random.default_rng(3)
    query = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    landmarks = rng.integers(0, 256, (25, 32), dtype=np.uint8)
    near = rng.integers(0, 40, (25, 8))
    dist = _window_distances(query, landmarks, near)
    bits = np.unpackbits(query, axis=1).astype(np.int64)[near]
    own = np.unpackbits(landmarks, axis=1).astype(np.int64)[:, None, :]
    assert np.array_equal(dist, np.abs(bits - own).sum(axis=2).astype(np.float64))


def test_window_distances_of_uint8_sift_are_l2_not_hamming():
    """SIFT descriptors are kept as uint8 (lossless): the guided window must compare them by
    L2 like their float32 originals, not as packed bits (a merge once sent them to the
    Hamming path, which moved bow+p3p's poses on 7scenes)."""
    from reloc_service.algorithms.pose.guided import _window_distances

    rng = np.random.default_rng(3)
    query = rng.integers(0, 256, (40, 128), dtype=np.uint8)
    landmarks = rng.integers(0, 256, (15, 128), dtype=np.uint8)
    near = rng.integers(0, 40, (15, 4))
    as_uint8 = _window_distances(query, landmarks, near)
    as_float = _window_distances(query.astype(np.float32), landmarks.astype(np.float32), near)
    np.testing.assert_allclose(as_uint8, as_float, rtol=1e-6)
    expected = np.linalg.norm(query[near].astype(np.float64)
                              - landmarks[:, None, :].astype(np.float64), axis=2)
    np.testing.assert_allclose(as_uint8, expected, rtol=1e-5)


def _windows(rng: np.random.Generator, n_query: int, rows: int, k: int) -> np.ndarray:
    """(rows, k) window keypoints with empty slots (``n_query``, as cKDTree marks them),
    repeated keypoints (equal distances) and rows with no keypoint at all."""
    near = rng.integers(0, n_query, (rows, k))
    near[rng.random((rows, k)) < 0.3] = n_query
    near[: rows // 10] = n_query
    if k > 1:
        near[rows // 10: rows // 5, 1] = near[rows // 10: rows // 5, 0]
    return np.sort(near, axis=1)     # cKDTree lists empty slots last


@pytest.mark.parametrize("width,k", [(32, 8), (32, 1), (128, 8), (128, 2)])
def test_compiled_window_test_is_the_numpy_choice(width, k, monkeypatch):
    """The compiled window pass gives the numpy path's smallest and next distances (the same
    dtype and values) and the same slot, the first of equal ones, for ORB's Hamming and
    uint8 SIFT's L2, with empty slots, repeated keypoints and empty windows."""
    pytest.importorskip("numba")
    from reloc_service.algorithms.pose import guided

    rng = np.random.default_rng(width + k)
    query = rng.integers(0, 256, (300, width), dtype=np.uint8)
    landmarks = rng.integers(0, 256, (2000, width), dtype=np.uint8)
    landmarks[::7] = query[rng.integers(0, 300, len(landmarks[::7]))]   # exact matches too
    near = _windows(rng, len(query), len(landmarks), k)
    compiled = guided._window_best(query, landmarks, near)
    monkeypatch.setattr(guided, "compiled", lambda: None)
    plain = guided._window_best(query, landmarks, near)
    for a, b in zip(compiled, plain, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert (compiled[2] == -1).any() and np.isinf(compiled[1]).any()


def test_a_map_of_float_sift_against_uint8_queries_takes_the_numpy_path(monkeypatch):
    """Client-given float descriptors in the map (not integers) are not truncated to the
    query's uint8: the compiled pass is only for two sides of one dtype."""
    pytest.importorskip("numba")
    from reloc_service.algorithms.pose import guided

    rng = np.random.default_rng(4)
    query = rng.integers(0, 256, (50, 128), dtype=np.uint8)
    landmarks = rng.uniform(0, 255, (80, 128)).astype(np.float32)
    near = _windows(rng, len(query), len(landmarks), 8)
    mixed = guided._window_best(query, landmarks, near)
    monkeypatch.setattr(guided, "compiled", lambda: None)
    plain = guided._window_best(query, landmarks, near)
    for a, b in zip(mixed, plain, strict=True):
        assert np.array_equal(a, b)


def test_compiled_background_distance_is_the_numpy_quantile(monkeypatch):
    """ORB's background distance from the compiled histogram equals numpy's quantile of the
    same pairs (to rounding), so every window verdict is the same."""
    pytest.importorskip("numba")
    from reloc_service.algorithms.pose import guided

    rng = np.random.default_rng(11)
    for n_query, n_map in [(500, 4000), (3, 5), (1, 1)]:
        query = rng.integers(0, 256, (n_query, 32), dtype=np.uint8)
        landmarks = rng.integers(0, 256, (n_map, 32), dtype=np.uint8)
        for quantile in (0.0, 0.01, 0.3, 0.5, 0.77, 1.0):
            compiled = guided.background_distance(query, landmarks, quantile)
            with monkeypatch.context() as m:
                m.setattr(guided, "compiled", lambda: None)
                plain = guided.background_distance(query, landmarks, quantile)
            assert compiled == pytest.approx(plain, rel=1e-12, abs=1e-12)


def test_keypoint_tree_is_built_once_per_features():
    from reloc_service.algorithms.pose.guided import keypoint_tree

    px = np.random.default_rng(3).uniform(0, 100, (50, 2))
    feats = Features.create("sift", px, np.zeros((50, 128), np.uint8))
    assert keypoint_tree(feats) is keypoint_tree(feats)
    assert keypoint_tree(feats).n == 50


def test_histogram_quantile_is_numpys_quantile():
    from reloc_service.algorithms.pose.guided import _histogram_quantile

    rng = np.random.default_rng(2)
    for n in (1, 2, 7, 65536):
        values = rng.integers(0, 40, n)
        counts = np.bincount(values, minlength=257)
        for quantile in rng.random(20):
            assert _histogram_quantile(counts, quantile) == pytest.approx(
                np.quantile(values, quantile), rel=1e-12, abs=1e-12)
