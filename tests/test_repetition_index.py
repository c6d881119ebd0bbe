"""The repetition check's index over every landmark of a map: the same twins and ratio-test
matches as a full scan, a per-query cost that does not grow with the map, and the pool made
when the map is prepared rather than by the first query."""

from __future__ import annotations

import functools
import itertools

import cv2
import numpy as np
import pytest

from reloc_service.algorithms.pose import repetition_kernels
from reloc_service.algorithms.pose.landmark_pool import LandmarkPool
from reloc_service.algorithms.pose.repetition import (
    RepetitionConf,
    twin_correspondences,
    unexplained_matches,
)
from reloc_service.algorithms.pose.repetition_index import IndexConf, RepetitionIndex
from reloc_service.core import features as feature_lib
from reloc_service.core.frame import Features
from reloc_service.tools.synth.planar import texture_mosaic

#: Every pool below is indexed (no full scan), in leaves of a few dozen rows.
INDEXED = IndexConf(exact_rows=0, leaf_rows=32)
EXACT = IndexConf(exact_rows=10**9)


@functools.cache
def tiles() -> list[np.ndarray]:
    mosaic = texture_mosaic()
    return [mosaic[r:r + 512, c:c + 512] for r in (0, 512) for c in (0, 512, 1024)]


@functools.cache
def extract(kind: str, tile: int, warped: bool = False) -> Features:
    image = tiles()[tile]
    if warped:  # the same picture seen again: turned 4 degrees and 5% nearer
        turn = cv2.getRotationMatrix2D((256.0, 256.0), 4.0, 1.05)
        image = cv2.warpAffine(image, turn, (512, 512), borderMode=cv2.BORDER_REFLECT)
    return feature_lib.extract(image, feature_lib.FeatureConf(kind=kind, max_features=600))


def copied_picture_pool(kind: str) -> tuple[LandmarkPool, int]:
    """Landmarks of five pictures on a wall, the first of them twice (a copy 2 m along):
    the pool and the row where the copy starts."""
    parts = [extract(kind, t) for t in range(5)] + [extract(kind, 0)]
    desc = np.concatenate([f.descriptors for f in parts])
    points = np.concatenate([np.c_[f.keypoints_px / 256.0, np.zeros(len(f))] + [i * 0.5, 0, 0]
                             for i, f in enumerate(parts)])
    points[-len(parts[-1]):] = points[:len(parts[0])] + [2.0, 0.0, 0.0]
    n = len(desc)
    return (LandmarkPool(desc, np.arange(n, dtype=np.int64) + 1000, points,
                         np.zeros(n, np.int64)), n - len(parts[-1]))


def inliers_on_first_copy(kind: str, pool: LandmarkPool, copy_start: int
                          ) -> tuple[Features, np.ndarray, np.ndarray]:
    """The query (the first picture, warped) matched to the pool without the copy, as the
    pose was solved: query keypoints and landmark ids."""
    query = extract(kind, 0, warped=True)
    q, rows, _ = feature_lib.match_ratio(query.descriptors, pool.descriptors[:copy_start])
    return query, q, pool.landmark_ids[rows]


def no_sigma(rows: np.ndarray) -> np.ndarray:
    return np.zeros(len(rows))


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_the_index_finds_the_twins_a_full_scan_finds(kind: str) -> None:
    pool, copy_start = copied_picture_pool(kind)
    query, q, ids = inliers_on_first_copy(kind, pool, copy_start)
    conf = RepetitionConf()
    exact = twin_correspondences(query, q, ids, pool, RepetitionIndex.build(pool.descriptors,
                                                                            EXACT),
                                 no_sigma, conf)
    index = RepetitionIndex.build(pool.descriptors, INDEXED)
    assert index.tree is not None
    found = twin_correspondences(query, q, ids, pool, index, no_sigma, conf)
    assert len(exact[0]) >= 30 and np.all(exact[1] >= copy_start)  # the copy's landmarks
    pairs = set(zip(*exact, strict=True))
    agree = len(pairs & set(zip(*found, strict=True))) / len(pairs)
    assert agree >= 0.95, f"the index found {agree:.0%} of the twins a full scan finds"


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_the_index_gives_the_ratio_test_matches_of_a_full_scan(kind: str) -> None:
    pool, _ = copied_picture_pool(kind)
    query = extract(kind, 1, warped=True)   # a picture seen once in the pool
    conf = RepetitionConf()
    none = np.zeros(0, np.int64)
    exact = unexplained_matches(query, none, RepetitionIndex.build(pool.descriptors, EXACT),
                                conf)
    found = unexplained_matches(query, none, RepetitionIndex.build(pool.descriptors, INDEXED),
                                conf)
    assert len(exact) >= 30
    # The matches a full scan makes are found too (a missed second neighbour can only add
    # matches, never take one away from a keypoint whose nearest is found).
    assert len(np.intersect1d(exact, found)) >= 0.95 * len(exact)


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_the_index_keeps_the_two_nearest_of_its_leaves_ties_to_the_first_scanned(
        kind: str) -> None:
    # The pool holds a picture twice (equal descriptors: ties): each query descriptor's two
    # nearest among the rows of the leaves it probes, a tie going to the row scanned first
    # (leaves in ascending order, rows in filing order), as one sorted scan of those rows.
    pool, _ = copied_picture_pool(kind)
    index = RepetitionIndex.build(pool.descriptors, INDEXED)
    query = extract(kind, 0, warped=True).descriptors
    d, rows = index.nearest_two(query)
    ties = 0
    for q, leaves in enumerate(index._probe(query)):
        scanned = np.concatenate([index.order[index.offsets[leaf]:index.offsets[leaf + 1]]
                                  for leaf in np.unique(leaves[leaves >= 0])]).astype(np.int64)
        dist = feature_lib.descriptor_distance(np.repeat(query[q:q + 1], len(scanned), axis=0),
                                               pool.descriptors[scanned])
        pick = np.argsort(dist, kind="stable")[:2]
        ties += int(dist[pick[0]] == dist[pick[1]])
        np.testing.assert_array_equal(rows[q], scanned[pick])
        np.testing.assert_allclose(d[q], dist[pick], rtol=1e-6)
    assert ties >= 10  # the tie-break is exercised


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_the_compiled_leaf_scan_gives_the_numpy_scans_distances_and_rows(kind: str,
                                                                        monkeypatch) -> None:
    """The compiled scan (:mod:`.repetition_kernels`) finds, value for value, what the numpy
    scan of each probed leaf does: on the copied picture (equal descriptors: ties across
    leaves and within one) and on leaves of a single row."""
    pytest.importorskip("numba")
    pool, _ = copied_picture_pool(kind)
    query = np.concatenate([extract(kind, 0, warped=True).descriptors,
                            extract(kind, 0).descriptors[:50]])
    for conf in (INDEXED, IndexConf(exact_rows=0, leaf_rows=2)):
        index = RepetitionIndex.build(pool.descriptors, conf)
        assert index._scan_compiled(query, index._probe(query)) is not None
        compiled = index.nearest_two(query)
        with monkeypatch.context() as m:
            m.setattr(repetition_kernels, "compiled", lambda: None)
            plain = index.nearest_two(query)
        np.testing.assert_array_equal(compiled[1], plain[1])
        np.testing.assert_array_equal(compiled[0], plain[0])
        assert compiled[0].dtype == plain[0].dtype == np.float32
        assert np.any(compiled[0][:, 0] == compiled[0][:, 1])  # ties were met
    sizes = np.diff(index.offsets)
    assert np.any(sizes == 1)  # one-row leaves too


def test_a_small_pool_is_scanned_in_full_as_before() -> None:
    pool, _ = copied_picture_pool("orb")
    index = RepetitionIndex.build(pool.descriptors, IndexConf(exact_rows=len(pool.descriptors)))
    query = extract("orb", 1, warped=True)
    assert index.tree is None
    assert np.all(index.scanned_rows(query.descriptors) == len(pool.descriptors))
    d, rows = index.nearest_two(query.descriptors)
    d_all, rows_all = feature_lib.nearest_two(query.descriptors, pool.descriptors)
    np.testing.assert_array_equal(rows, rows_all)
    np.testing.assert_allclose(d, d_all)


def test_the_cost_of_a_query_does_not_grow_with_the_pool() -> None:
    """Four times the landmarks: each query descriptor is compared with about as many rows
    (leaves of a fixed size, a fixed number of them probed), far fewer than the pool."""
    rng = np.random.default_rng(0)
    conf = IndexConf(exact_rows=0, leaf_rows=64)
    base = rng.integers(0, 256, (32000, 32), dtype=np.uint8)
    query = base[rng.integers(0, len(base), 200)]
    small = RepetitionIndex.build(base[:8000], conf).scanned_rows(query).mean()
    large = RepetitionIndex.build(base, conf).scanned_rows(query).mean()
    assert large < 2.0 * small, (small, large)
    assert large < 0.1 * len(base)


def test_a_pool_with_fewer_than_two_rows_finds_what_is_there() -> None:
    one = RepetitionIndex.build(np.full((1, 32), 7, np.uint8))
    d, rows = one.nearest_two(np.full((2, 32), 7, np.uint8))
    np.testing.assert_array_equal(rows, [[0, -1], [0, -1]])
    assert np.all(d[:, 0] == 0) and np.all(np.isinf(d[:, 1]))


def test_bad_index_options_say_what_is_expected() -> None:
    with pytest.raises(ValueError, match="expected exact_rows >= 0"):
        IndexConf(exact_rows=-1)


def test_the_map_pool_is_made_when_the_map_is_prepared_not_by_a_query(monkeypatch) -> None:
    from reloc_service.algorithms.pose.p3p import P3PPoseFinder
    from reloc_service.tools.synth.planar import keyframe_grid, planar_scene

    scene = planar_scene(keyframe_grid(3, 2), kinds=("orb",), max_features=300)
    finder = P3PPoseFinder(P3PPoseFinder.Conf(kind="orb", max_features=300))
    state = scene.map.snapshot()
    finder.prepare_map(state)
    made: list[int] = []
    real_build = RepetitionIndex.build
    monkeypatch.setattr(RepetitionIndex, "build",
                        lambda *a, **k: made.append(1) or real_build(*a, **k))
    pool, index, ids = finder._map_pool(state)
    assert not made, "the first query gathered the map's pool again"
    assert ids == list(state.keyframes) and len(pool.landmark_ids) == state.landmark_count("orb")
    assert index.descriptors is pool.descriptors      # the index holds no copy of them


def test_finders_of_one_kind_share_the_pool_which_goes_with_its_map_state() -> None:
    import dataclasses
    import gc

    from reloc_service.algorithms.pose import map_pool
    from reloc_service.algorithms.pose.p3p import P3PPoseFinder
    from reloc_service.tools.synth.planar import keyframe_grid, planar_scene

    scene = planar_scene(keyframe_grid(2, 2), kinds=("orb",), max_features=200)
    half = P3PPoseFinder(P3PPoseFinder.Conf(kind="orb", max_features=200, query_scale=0.5))
    full = P3PPoseFinder(P3PPoseFinder.Conf(kind="orb", max_features=200))
    state = dataclasses.replace(scene.map.snapshot())    # a state only this test holds
    assert half._map_pool(state)[0] is full._map_pool(state)[0]
    # Its own entries, by key: a collection may free other tests' states' pools too.
    own = [key for key in map_pool._POOLS if key[0] == id(state)]
    assert len(own) == 1    # one pool for both finders
    del state
    gc.collect()
    assert not set(own) & set(map_pool._POOLS)


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_a_map_pool_read_keyframe_by_keyframe_is_the_pool_gathered_at_once(kind: str) -> None:
    """The whole map's pool, each keyframe's features dropped once read, holds the rows the
    gathering of every keyframe at once holds, in the same order (keyframes in any order:
    the first to see a landmark gives its row), and stops when cancelled."""
    from reloc_service.core.errors import Cancelled
    from reloc_service.tools.synth.planar import keyframe_grid, planar_scene

    scene = planar_scene(keyframe_grid(3, 2), kinds=(kind,), max_features=300)
    state = scene.map.snapshot()
    keyframes = list(state.keyframes.values())
    seen_twice = 0
    for order in (keyframes, keyframes[::-1], keyframes[2:] + keyframes[:2], keyframes[3:4]):
        at_once = LandmarkPool.gather(order, kind)
        streamed = LandmarkPool.gather_streamed(order, kind)
        for field in ("descriptors", "landmark_ids", "points_world", "keyframe_rows"):
            np.testing.assert_array_equal(getattr(streamed, field), getattr(at_once, field))
        observed = sum(int((kf.features[kind].landmark_ids >= 0).sum()) for kf in order)
        seen_twice = max(seen_twice, observed - len(at_once.landmark_ids))
    assert seen_twice > 0, "no landmark seen by two keyframes: nothing to keep once"
    calls: list[int] = []
    with pytest.raises(Cancelled):
        LandmarkPool.gather_streamed(keyframes, kind, lambda: calls.append(1) or len(calls) > 2)
    assert len(calls) == 3


@pytest.mark.parametrize("parts", [
    {}, {"descriptors": "per-landmark"}, {"descriptors": "landmarks", "descriptor_codec": "pq"},
    {"descriptors": "landmarks", "descriptor_codec": "pq-hybrid"},
    {"descriptors": "per-landmark", "descriptor_codec": "pq-hybrid"}])
def test_a_stored_maps_pool_decodes_its_landmark_rows_only_into_the_same_pool(
        tmp_path, monkeypatch, parts) -> None:
    """Of a map loaded from a snapshot (each way of storing descriptors), the pool that
    decodes only the rows it keeps, several keyframes at a time, is the pool of every
    keyframe's features read whole: keyframes in any order, read in runs of any length,
    with some keyframes' features built (read alone, between runs); no keyframe's features
    are built by it."""
    from reloc_service.algorithms.pose import landmark_pool
    from reloc_service.storage.keyframe_parts import StoredParts
    from reloc_service.storage.snapshot import load_map, save_map
    from reloc_service.tools.synth.planar import keyframe_grid, planar_scene

    scene = planar_scene(keyframe_grid(3, 2), kinds=("orb", "sift"), max_features=300)
    save_map(scene.map.snapshot(), tmp_path / "map", parts=StoredParts(**parts))
    state, _ = load_map(tmp_path / "map")
    keyframes = list(state.keyframes.values())
    orders = (keyframes, keyframes[::-1], keyframes[2:] + keyframes[:2])

    def same_pools() -> None:
        for kind, order in itertools.product(("orb", "sift"), orders):
            at_once = LandmarkPool.gather(order, kind)
            streamed = LandmarkPool.gather_streamed(order, kind)
            assert len(at_once.landmark_ids) > 0
            for field in ("descriptors", "landmark_ids", "points_world", "keyframe_rows"):
                np.testing.assert_array_equal(getattr(streamed, field),
                                              getattr(at_once, field))

    for run in (landmark_pool.STORED_RUN, 2, 1):
        monkeypatch.setattr(landmark_pool, "STORED_RUN", run)
        same_pools()
    monkeypatch.setattr(landmark_pool, "READ_CHUNK_ROWS", 7)   # rows read in small chunks
    same_pools()
    assert not any(kf.features.built_kinds for kf in keyframes)
    for kf in keyframes[1::3]:
        kf.features["sift"]
    monkeypatch.setattr(landmark_pool, "STORED_RUN", 2)
    same_pools()


def test_a_stored_maps_pool_holds_little_beyond_itself_while_it_is_read(tmp_path,
                                                                         monkeypatch) -> None:
    """Reading a stored map's pool one keyframe at a time holds, beyond the pool itself,
    about one keyframe's rows at a time (tracemalloc, which numpy reports to), not the pool's
    rows a second time (as parts concatenated at the end did)."""
    import tracemalloc

    from reloc_service.algorithms.pose import landmark_pool
    from reloc_service.storage.snapshot import load_map, save_map
    from reloc_service.tools.synth.planar import keyframe_grid, planar_scene

    scene = planar_scene(keyframe_grid(5, 4), kinds=("sift",), max_features=300)
    save_map(scene.map.snapshot(), tmp_path / "map")
    state, _ = load_map(tmp_path / "map")
    keyframes = list(state.keyframes.values())
    monkeypatch.setattr(landmark_pool, "STORED_RUN", 1)
    LandmarkPool.gather_streamed(keyframes, "sift")   # one-off work (shared indexes) first
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        pool = LandmarkPool.gather_streamed(keyframes, "sift")
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    pool_bytes = sum(a.nbytes for a in (pool.descriptors, pool.landmark_ids, pool.points_world,
                                        pool.keyframe_rows))
    assert held - before >= pool_bytes
    # one keyframe's rows decoded (every field, and the copies decoding makes) and the rows
    # chosen: 0.43 times the pool of these twenty keyframes; parts concatenated at the end
    # held the pool's rows a second time (more than 1.0)
    assert peak - held < 0.6 * pool_bytes, (peak - held, pool_bytes)
