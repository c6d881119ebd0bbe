"""The local map a tracker matches against: a keyframe set's pool put together from its
keyframes' kept parts is, row for row, the pool gathered and weighed afresh."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from reloc_service.algorithms.pose.landmark_pool import LandmarkPool
from reloc_service.algorithms.relocalizers.tracking_local_map import (
    LocalMaps,
    landmark_uncertainty,
)
from reloc_service.core.geometry import pose_covariance_from_sigmas


def _fresh(state, near, kind):
    keyframes = [state.keyframes[k] for k in near]
    pool = LandmarkPool.gather(keyframes, kind)
    return pool, landmark_uncertainty(pool, state, near, keyframes)


def _assert_same(made, fresh):
    (pool, unc), (pool0, unc0) = made, fresh
    for name in ("descriptors", "landmark_ids", "points_world", "keyframe_rows"):
        a, b = getattr(pool, name), getattr(pool0, name)
        assert a.dtype == b.dtype, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    np.testing.assert_array_equal(unc.depth_sigmas_m, unc0.depth_sigmas_m)
    np.testing.assert_array_equal(unc.ray_origins_world, unc0.ray_origins_world)


@pytest.mark.parametrize("uncertain", [False, True])
def test_pools_from_kept_keyframe_parts_are_the_pools_gathered_afresh(synthetic_scene,
                                                                       synthetic_map,
                                                                       uncertain):
    state = synthetic_map
    if uncertain:
        # every keyframe but one stated 1 cm / 0.3 deg off: the widening differs by keyframe
        covs = {k: pose_covariance_from_sigmas(0.01, np.deg2rad(0.3))
                for k in list(state.keyframes)[1:]}
        state = dataclasses.replace(state, keyframes={
            k: dataclasses.replace(kf, pose_covariance=covs.get(k))
            for k, kf in state.keyframes.items()})
    kind = next(k for k in ("orb", "sift") if any(
        k in kf.features for kf in state.keyframes.values()))
    maps = LocalMaps()
    rng = np.random.default_rng(0)
    sets = []
    for pose in synthetic_scene.query_poses:
        near = state.nearest_keyframes(pose, 10, 60.0)
        # the same keyframes in other orders and fewer of them: other pools, the same parts
        sets += [near, near[::-1], list(rng.permutation(near)), near[: max(1, len(near) // 2)],
                 near[:1]]
    for near in sets:
        near = [int(k) for k in near]
        made = maps.get(state, near, [state.keyframes[k] for k in near], kind)
        _assert_same(made, _fresh(state, near, kind))
    # Shared landmarks exist: a keyframe's row of one is dropped when a better one sees it.
    near = [int(k) for k in sets[0]]
    whole = sum(int(np.sum(state.keyframes[k].features[kind].landmark_ids >= 0)) for k in near)
    assert len(_fresh(state, near, kind)[0].landmark_ids) < whole
