"""The map's dispersion (:mod:`reloc_service.algorithms.pose.map_consistency`) on a map with
mis-associated landmarks: the robust estimate an answer states keeps to the honest map's,
the plain one a decision weighs grows with them."""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

import numpy as np

from reloc_service.algorithms.pose.held_out import held_out_candidates, held_out_points
from reloc_service.algorithms.pose.map_consistency import (
    _STATISTICS,
    excess_exclusion,
    gated_inliers,
    keyframe_statistic,
    map_dispersion,
    prepare_map,
)
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.core import distributions as stats
from reloc_service.core.map import MapState


def mis_associated(state: MapState, share: float, shift_px: float, seed: int) -> MapState:
    """``state`` with ``share`` of each keyframe's landmark observations moved ``shift_px``
    away from the image centre: the keypoint of a neighbouring copy of a repeated texture
    associated in place of the landmark's own (inside the consensus threshold, beyond the
    keypoint noise), radial so that it looks like a focal error to the intrinsics test."""
    rng = np.random.default_rng(seed)
    keyframes = {}
    for kf_id, keyframe in state.keyframes.items():
        feats = keyframe.features["sift"]
        observed = np.flatnonzero(feats.landmark_ids >= 0)
        wrong = rng.choice(observed, int(share * len(observed)), replace=False)
        px = feats.keypoints_px.astype(np.float64).copy()
        centre = np.array([keyframe.camera.cx, keyframe.camera.cy])
        radial = px[wrong] - centre
        radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
        px[wrong] += shift_px * radial
        keyframes[kf_id] = keyframe.with_features(
            "sift", dataclasses.replace(feats, keypoints_px=px.astype(feats.keypoints_px.dtype)))
    return dataclasses.replace(state, keyframes=MappingProxyType(keyframes))


def test_the_robust_dispersion_ignores_mis_associated_landmarks(synthetic_map):
    conf = PnPConf()
    ids = synthetic_map.keyframe_ids()
    wrong = mis_associated(synthetic_map, share=0.1, shift_px=3.0, seed=3)
    plain = (map_dispersion(synthetic_map, "sift", ids, conf),
             map_dispersion(wrong, "sift", ids, conf))
    robust = (map_dispersion(synthetic_map, "sift", ids, conf, robust=True),
              map_dispersion(wrong, "sift", ids, conf, robust=True))
    assert plain[1] > 2.0 * plain[0]
    assert robust[1] < 1.5 * robust[0]


def fresh_features(state: MapState) -> MapState:
    """``state`` with new (equal) feature objects: nothing cached with the old ones."""
    keyframes = {k: kf.with_features("sift", dataclasses.replace(kf.features["sift"]))
                 for k, kf in state.keyframes.items()}
    return dataclasses.replace(state, keyframes=MappingProxyType(keyframes))


def test_prepare_map_caches_both_statistics_as_each_computed_alone(synthetic_map):
    # Computed together at map preparation (one set of held-out points for both), each
    # keyframe's plain and gated statistics equal those computed alone, on a map where the
    # gate leaves out more than honest residuals explain (the two differ). The keyframes
    # where they do not are the real sets' (their answers compared per query).
    wrong = mis_associated(synthetic_map, share=0.1, shift_px=3.0, seed=3)
    alone_conf = dataclasses.replace(PnPConf(), robust_stated_dispersion=False)
    ids = wrong.keyframe_ids()
    plain_state, robust_state, prepared = (fresh_features(wrong) for _ in range(3))
    plain = [keyframe_statistic(plain_state, k, "sift", alone_conf) for k in ids]
    robust = [keyframe_statistic(robust_state, k, "sift", alone_conf, robust=True) for k in ids]
    prepare_map(prepared, "sift", PnPConf())
    differ = [p != r for p, r in zip(plain, robust, strict=True)]
    assert any(differ)
    assert all(set(_STATISTICS[prepared.keyframes[k].features["sift"]]) == {False, True}
               for k in ids)  # both cached, so a query computes neither
    assert [keyframe_statistic(prepared, k, "sift", alone_conf) for k in ids] == plain
    assert [keyframe_statistic(prepared, k, "sift", alone_conf, robust=True)
            for k in ids] == robust


def test_the_gate_keeps_honest_residuals_at_its_false_alarm_rate():
    rng = np.random.default_rng(0)
    squared = 4.0 * rng.chisquare(2, 20000)  # honest residuals, a scale of 4 unknown to it
    kept = gated_inliers(squared, np.arange(len(squared)), false_alarm=0.01)
    assert abs(1.0 - len(kept) / len(squared) - 0.01) < 0.003
    outliers = np.concatenate([squared, np.full(2000, 4.0 * stats.chi2.isf(1e-4, 2))])
    kept = gated_inliers(outliers, np.arange(len(outliers)), false_alarm=0.01)
    assert kept.max() < len(squared)  # every outlier left out


def _flag_rate(rng: np.random.Generator, share: float, keyframes: int = 1000,
               held_out: int = 300) -> float:
    """The share of simulated keyframes (``held_out`` residuals each, ``share`` of them
    mis-associated: beyond the gate) whose gate :func:`excess_exclusion` flags."""
    limit = stats.chi2.isf(0.01, 2)
    flags = []
    for _ in range(keyframes):
        squared = rng.chisquare(2, held_out)
        wrong = int(share * held_out)
        squared[:wrong] = rng.uniform(2.0 * limit, 10.0 * limit, wrong)
        kept = gated_inliers(squared, np.arange(held_out))
        flags.append(excess_exclusion(held_out - len(kept), held_out))
    return float(np.mean(flags))


def test_the_exclusion_test_flags_honest_keyframes_near_its_false_alarm_rate():
    # 1 % nominal; the scale estimated from the same residuals adds a little.
    assert _flag_rate(np.random.default_rng(1), share=0.0) < 0.03


def test_the_exclusion_test_flags_keyframes_with_mis_associated_landmarks():
    assert _flag_rate(np.random.default_rng(2), share=0.05, keyframes=200) > 0.95


def test_the_exclusion_test_keeps_the_nominal_count():
    assert not excess_exclusion(3, 300)   # the gate's expected count at 1 %
    assert not excess_exclusion(0, 300)
    assert excess_exclusion(15, 300)      # 5 %: P(X >= 15) is about 1e-6


def test_held_out_depth_landmarks_keep_the_point_another_keyframe_measured(panning_depth_map):
    """On a depth map of a camera panning in place (conftest), a held-out keyframe's
    landmarks lifted from another keyframe's depth are held at that measured point, and those
    lifted from its own depth map are left out: re-triangulated from keyframes a few
    millimetres apart they land anywhere along their rays, and the held-out statistic would
    read that as the map's own dispersion."""
    state = panning_depth_map.state
    cols = state.landmarks.columns()
    assert np.all(cols.depth_sigmas_m == 0)                 # every landmark from depth
    kept = own = 0
    for kf_id in state.keyframe_ids():
        feats = state.keyframes[kf_id].features["sift"]
        _, rows = held_out_candidates(cols, feats.landmark_ids)
        points, held = held_out_points(state, cols, rows, kf_id, "sift")
        assert np.array_equal(points[held], cols.points_world[rows[held]])
        kept, own = kept + int(held.sum()), own + int((~held).sum())
    assert kept > 100 and own > 0     # measured elsewhere; lifted from the keyframe itself
    dispersion = map_dispersion(state, "sift", state.keyframe_ids(), PnPConf())
    assert dispersion < 3.0, dispersion
