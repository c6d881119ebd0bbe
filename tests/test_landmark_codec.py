"""Landmark geometry on disk: float32 offsets from the anchor keyframe only where the rounding
is below ROUNDING_SHARE of every landmark's uncertainty."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from reloc_service.storage.landmark_codec import (
    ANCHORED_POINTS,
    HALF_ROUNDING_SHARE,
    ROUNDING_SHARE,
    WidenedColumn,
    anchored_points,
    anchors,
    decode_points,
    encode_geometry,
    position_sigmas,
)


def test_anchored_float32_is_within_the_share_of_each_sigma(synthetic_map):
    columns = synthetic_map.landmarks.columns()
    stored = encode_geometry(columns, synthetic_map.keyframes)
    assert set(stored) == {ANCHORED_POINTS, "depth_sigmas_m"}
    assert stored[ANCHORED_POINTS].dtype == np.float32 == stored["depth_sigmas_m"].dtype
    points = decode_points(stored[ANCHORED_POINTS], columns.obs_offsets, columns.obs_keyframe,
                           synthetic_map.keyframes)
    centres, focal = anchors(columns, synthetic_map.keyframes)
    allowed = ROUNDING_SHARE * position_sigmas(columns.points_world, centres, focal,
                                               columns.depth_sigmas_m)
    error = np.linalg.norm(points - columns.points_world, axis=1)
    assert points.dtype == np.float64 and np.all(error <= allowed) and error.max() > 0
    # the anchor is a camera that saw the landmark: the range, not the world position, counts
    ranges = np.linalg.norm(columns.points_world - centres, axis=1)
    assert ranges.max() < 10 and np.all(error <= ranges * 2.0**-23)


def test_float16_offsets_are_within_half_of_each_sigma_else_float32(synthetic_map):
    """``half``: float16 offsets where every landmark's rounding is within
    HALF_ROUNDING_SHARE of its uncertainty (the test camera's, with unknown sigmas: the
    0.5 px floor); a focal length 8 times larger shrinks that floor below float16's rounding
    and the map keeps float32, within ROUNDING_SHARE as before."""
    columns = synthetic_map.landmarks.columns()
    unknown = dataclasses.replace(columns, depth_sigmas_m=np.zeros(len(columns)))
    stored = encode_geometry(unknown, synthetic_map.keyframes, half=True)
    assert stored[ANCHORED_POINTS].dtype == np.float16
    assert stored["depth_sigmas_m"].dtype == np.float32
    points = decode_points(stored[ANCHORED_POINTS], columns.obs_offsets, columns.obs_keyframe,
                           synthetic_map.keyframes)
    centres, focal = anchors(columns, synthetic_map.keyframes)
    sigma = position_sigmas(columns.points_world, centres, focal, unknown.depth_sigmas_m)
    error = np.linalg.norm(points - columns.points_world, axis=1)
    assert np.all(error <= HALF_ROUNDING_SHARE * sigma) and np.any(error > ROUNDING_SHARE * sigma)
    sharp = {k: dataclasses.replace(kf, camera=dataclasses.replace(kf.camera, fx=8 * kf.camera.fx,
                                                                    fy=8 * kf.camera.fy))
             for k, kf in synthetic_map.keyframes.items()}
    assert encode_geometry(unknown, sharp, half=True)[ANCHORED_POINTS].dtype == np.float32


def test_unknown_sigmas_use_the_pixel_floor_and_huge_focal_lengths_keep_float64(synthetic_map):
    """Landmarks of unknown sigma (0) are bounded by a 0.5 px keypoint at their range: with
    the test camera that allows float32; a focal length of 1e9 px would not, so the map keeps
    its float64 columns, exactly."""
    columns = synthetic_map.landmarks.columns()
    unknown = dataclasses.replace(columns, depth_sigmas_m=np.zeros(len(columns)))
    assert ANCHORED_POINTS in encode_geometry(unknown, synthetic_map.keyframes)
    sharp = {k: dataclasses.replace(kf, camera=dataclasses.replace(kf.camera, fx=1e9, fy=1e9))
             for k, kf in synthetic_map.keyframes.items()}
    kept = encode_geometry(unknown, sharp)
    assert set(kept) == {"points_world", "depth_sigmas_m"}
    assert kept["points_world"].dtype == np.float64
    assert np.array_equal(kept["points_world"], columns.points_world)



def test_a_map_far_from_the_origin_is_anchored_where_world_float32_would_not_fit(synthetic_map):
    """3 km from the origin (a UTM-like frame), world float32 moves unknown-sigma landmarks by more than the
    share allows; offsets from their anchors do not."""
    shift = np.array([3000.0, -2000.0, 50.0])
    columns = synthetic_map.landmarks.columns()
    far = dataclasses.replace(columns, points_world=columns.points_world + shift,
                              depth_sigmas_m=np.zeros(len(columns)))
    keyframes = {}
    for k, kf in synthetic_map.keyframes.items():
        pose = kf.world_from_cam.copy()
        pose[:3, 3] += shift
        keyframes[k] = dataclasses.replace(kf, world_from_cam=pose)
    stored = encode_geometry(far, keyframes)
    assert ANCHORED_POINTS in stored
    centres, focal = anchors(far, keyframes)
    allowed = ROUNDING_SHARE * position_sigmas(far.points_world, centres, focal,
                                               far.depth_sigmas_m)
    world32 = far.points_world.astype(np.float32).astype(np.float64)
    assert np.any(np.linalg.norm(world32 - far.points_world, axis=1) > allowed)
    back = decode_points(stored[ANCHORED_POINTS], far.obs_offsets, far.obs_keyframe, keyframes)
    assert np.all(np.linalg.norm(back - far.points_world, axis=1) <= allowed)


def test_unanchored_landmarks_keep_float64_and_cannot_be_decoded(synthetic_map):
    columns = synthetic_map.landmarks.columns()
    offsets = columns.obs_offsets.copy()
    offsets[1] = offsets[0]                   # landmark 0 without observations
    lonely = dataclasses.replace(columns, obs_offsets=offsets)
    assert "points_world" in encode_geometry(lonely, synthetic_map.keyframes)
    with pytest.raises(ValueError, match="an observation per landmark"):
        decode_points(np.zeros((len(columns), 3), np.float32), offsets, columns.obs_keyframe,
                      synthetic_map.keyframes)
    nan = dataclasses.replace(columns, points_world=np.where(
        np.arange(len(columns))[:, None] == 3, np.nan, columns.points_world))
    assert "points_world" in encode_geometry(nan, synthetic_map.keyframes)


def test_anchored_points_decode_any_row_selection_like_the_whole_column(synthetic_map):
    """A loaded map's points are decoded per row: an index, slice, index array or mask gives
    exactly the rows of the full decode, and numpy functions see a (L, 3) float64 array."""
    columns = synthetic_map.landmarks.columns()
    stored = encode_geometry(columns, synthetic_map.keyframes)
    lazy = anchored_points(stored[ANCHORED_POINTS], columns.obs_offsets, columns.obs_keyframe,
                           synthetic_map.keyframes)
    full = np.asarray(lazy)
    assert full.dtype == np.float64 and full.shape == lazy.shape == (len(columns), 3)
    mask = np.arange(len(columns)) % 3 == 0
    for rows in (5, slice(2, 9), np.array([7, 0, 7, 3]), mask):
        assert np.array_equal(lazy[rows], full[rows])
    assert np.array_equal(np.concatenate([lazy, full[:2]]), np.concatenate([full, full[:2]]))
    sigmas = WidenedColumn(stored["depth_sigmas_m"])
    assert sigmas[[1, 2]].dtype == np.float64 and len(sigmas) == len(columns)
    assert np.array_equal(np.asarray(sigmas), stored["depth_sigmas_m"].astype(np.float64))
