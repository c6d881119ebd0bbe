"""Helpers shared by the snapshot tests (not a test module): a map state compared with its
saved-and-loaded copy, field by field (landmark points within the rounding the snapshot's
codec allows), the synthetic map enriched with a depth map and ORB features and the synthetic
map cut to its first keyframes."""

from __future__ import annotations

import numpy as np

from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.storage.feature_columns import ANGLELESS_KINDS, NO_ANGLE
from reloc_service.storage.landmark_codec import ROUNDING_SHARE, anchors, position_sigmas
from reloc_service.storage.snapshot import FEATURE_FIELDS


def assert_states_equal(a: MapState, b: MapState) -> None:
    """``b`` is ``a`` exactly, but for landmark points and sigmas: exact, or (stored as
    anchored float32) within the rounding :mod:`reloc_service.storage.landmark_codec` allows."""
    assert (a.version, a.next_landmark_id) == (b.version, b.next_landmark_id)
    assert a.keyframe_ids() == b.keyframe_ids()
    for k in a.keyframe_ids():
        ka, kb = a.keyframes[k], b.keyframes[k]
        assert ka.camera == kb.camera and ka.timestamp == kb.timestamp
        assert np.array_equal(ka.world_from_cam, kb.world_from_cam)
        assert np.array_equal(ka.image, kb.image) and kb.image.dtype == np.uint8
        assert (ka.depth is None) == (kb.depth is None)
        if ka.depth is not None:
            assert np.array_equal(ka.depth, kb.depth, equal_nan=True)
        assert sorted(ka.features) == sorted(kb.features)
        for kind in ka.features:
            for name in FEATURE_FIELDS:
                va, vb = getattr(ka.features[kind], name), getattr(kb.features[kind], name)
                assert va.dtype == vb.dtype, name
                if name == "points_world":
                    va = _as_loaded_points(a, b, ka.features[kind].landmark_ids, va, vb)
                if name == "angles" and (kind in ANGLELESS_KINDS or np.all(vb == NO_ANGLE)):
                    va = np.full_like(va, NO_ANGLE)   # not saved: OpenCV's "none"
                assert np.array_equal(va, vb, equal_nan=True), name
    assert sorted(a.landmarks) == sorted(b.landmarks)
    for i, lm in a.landmarks.items():
        assert lm.observations == b.landmarks[i].observations
    _assert_landmark_geometry_close(a, b)


def _as_loaded_points(a: MapState, b: MapState, ids: np.ndarray, points: np.ndarray,
                      loaded: np.ndarray) -> np.ndarray:
    """``points`` with each that is its landmark's point in ``a`` and was not loaded as it
    is (not a stored column) replaced by that landmark's point in ``b``: derived at load."""
    out = points.copy()
    has = np.flatnonzero((ids >= 0) & a.landmarks.contains(ids))
    derived = (np.all(a.landmark_points(ids[has]) == points[has], axis=1)
               & ~np.all(loaded[has] == points[has], axis=1))
    out[has[derived]] = b.landmark_points(ids[has[derived]])
    return out


def _assert_landmark_geometry_close(a: MapState, b: MapState) -> None:
    ids = np.array(sorted(a.landmarks), np.int64)
    pa, pb = a.landmark_points(ids), b.landmark_points(ids)
    sa, sb = a.landmark_sigmas(ids), b.landmark_sigmas(ids)
    found = anchors(a.landmarks.columns(), a.keyframes)
    if found is None:
        assert np.array_equal(pa, pb) and np.array_equal(sa, sb)
        return
    allowed = ROUNDING_SHARE * position_sigmas(pa, *found, sa)
    assert np.all(np.linalg.norm(pa - pb, axis=1) <= allowed)
    assert np.all(np.abs(sa - sb) <= allowed)


def enriched_state(synthetic_scene, synthetic_map: MapState) -> MapState:
    """The synthetic map with a depth map, a timestamp-less keyframe and ORB features too."""
    from reloc_service.core.features import FeatureConf, extract
    from reloc_service.core.mapping import MapBuilder

    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    kf = synthetic_map.keyframes[1]
    kmap.add_keyframe(kf.with_features("orb", extract(kf.image, FeatureConf("orb", 300))))
    MapBuilder(kmap).add_keyframe(9, synthetic_scene.query_images[0], synthetic_scene.camera,
                                  synthetic_scene.query_poses[0],
                                  depth=synthetic_scene.query_depths[0])
    return kmap.snapshot()


def tiny_state(synthetic_map: MapState, n: int) -> MapState:
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    for k in synthetic_map.keyframe_ids()[n:]:
        kmap.remove_keyframe(k)
    return kmap.snapshot()
