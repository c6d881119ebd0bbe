"""Triangulation: epipolar check, midpoint + refinement accuracy, every rejection rule,
keyframe-level triangulation with track extension, and landmarks from depth."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PINHOLE, RADTAN

from reloc_service.core.errors import ConfigError
from reloc_service.core.features import FeatureConf, extract
from reloc_service.core.frame import Keyframe
from reloc_service.core.geometry import invert, look_at, transform_points
from reloc_service.core.landmarks import (
    landmarks_from_depth,
    lift_pixels,
    sample_depth,
    triangulate_keyframe,
)
from reloc_service.core.map import KeyframeMap
from reloc_service.core.triangulation import (
    TrackStatus,
    TriangulationConf,
    ViewObservations,
    depth_uncertainty,
    epipolar_angles,
    keypoint_sigmas,
    refine_points,
    reprojection_errors,
    triangulate_midpoint,
    triangulate_tracks,
)


def _poses(offsets: list[float]) -> list[np.ndarray]:
    """Cameras on a sideways line (x offsets, metres) looking at (0, 3, 1)."""
    return [look_at((x, 0.0, 1.0), (0.0, 3.0, 1.0)) for x in offsets]


def _views(camera, poses, points_world, *, noise_px=0.0, seed=0) -> list[ViewObservations]:
    rng = np.random.default_rng(seed)
    views = []
    for pose in poses:
        cam_from_world = invert(pose)
        px = camera.project(transform_points(cam_from_world, points_world))
        px += rng.normal(0.0, noise_px, px.shape)
        views.append(ViewObservations(camera, cam_from_world, np.arange(len(points_world)), px))
    return views


#: Geometry tests with short baselines: no uncertainty rule (tested on its own).
LOOSE = TriangulationConf(max_depth_uncertainty=1.0)


def _points(n: int, seed: int = 0, depth: tuple[float, float] = (1.5, 3.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(*depth, n),
                            rng.uniform(0.6, 1.4, n)])


def test_epipolar_angles_separate_true_and_false_matches():
    pts = _points(50)
    a_pose, b_pose = _poses([0.0, 0.3])
    bearings_a = PINHOLE.unproject(PINHOLE.project(transform_points(invert(a_pose), pts)))
    bearings_b = PINHOLE.unproject(PINHOLE.project(transform_points(invert(b_pose), pts)))
    b_from_a = invert(b_pose) @ a_pose
    assert np.max(epipolar_angles(bearings_a, bearings_b, b_from_a)) < 1e-9
    shuffled = np.roll(bearings_b, 7, axis=0)
    assert np.median(epipolar_angles(bearings_a, shuffled, b_from_a)) > 5 * 2.0 / PINHOLE.fx


def test_epipolar_angles_without_baseline_use_the_ray_angle():
    pose = _poses([0.0])[0]
    b = PINHOLE.unproject(np.array([[100.0, 80.0], [200.0, 150.0]]))
    assert np.allclose(epipolar_angles(b, b, np.eye(4)), 0.0, atol=1e-7)
    assert epipolar_angles(b, b[::-1], invert(pose) @ pose)[0] > 0.1


@pytest.mark.parametrize("camera", [PINHOLE, RADTAN], ids=["pinhole", "radtan"])
def test_refined_points_are_accurate_at_two_metres(camera):
    # Depth sigma ~ z^2 sigma_px / (f b) = 4 * 0.3 / (250 * 0.8) = 6 mm at 2 m.
    pts = _points(300, depth=(1.8, 2.2))
    views = _views(camera, _poses([-0.4, 0.0, 0.4]), pts, noise_px=0.3)
    midpoint = triangulate_midpoint(views, len(pts))
    refined = refine_points(midpoint, views)
    err_mid = np.linalg.norm(midpoint - pts, axis=1)
    err_ref = np.linalg.norm(refined - pts, axis=1)
    assert np.median(err_ref) < 0.01
    assert np.median(err_ref) <= np.median(err_mid) + 1e-4
    # The refinement minimises the pixel error: never worse than the midpoint's.
    before = np.concatenate(reprojection_errors(midpoint, views))
    after = np.concatenate(reprojection_errors(refined, views))
    assert np.sum(after**2) <= np.sum(before**2) + 1e-9


def test_exact_observations_are_recovered_exactly():
    pts = _points(40)
    result = triangulate_tracks(_views(RADTAN, _poses([0.0, 0.3]), pts), len(pts), LOOSE)
    assert result.accepted.all()
    assert np.max(np.linalg.norm(result.points_world - pts, axis=1)) < 1e-6


def test_rejection_rules():
    conf = TriangulationConf(min_parallax_deg=1.5, max_reprojection_px=2.0,
                             max_depth_uncertainty=1.0)
    pts = _points(4, seed=3)
    poses = _poses([0.0, 0.3]) + [look_at((0.001, 0.0, 1.0), (0.0, 3.0, 1.0))]
    views = _views(PINHOLE, poses, pts)
    # Point 1: pixels whose rays meet behind both cameras (cheirality).
    behind_world = np.array([[0.2, -2.5, 1.1]])
    for v in views[:2]:
        p_cam = transform_points(v.cam_from_world, behind_world)
        v.pixels_px[1] = PINHOLE.normalized_to_pixels(p_cam[:, :2] / p_cam[:, 2:])[0]
    # Point 2: a bad match, 12 px off the (horizontal) epipolar line in the second view.
    views[1].pixels_px[2] += (0.0, 12.0)
    # Point 3: seen by the reference and by a camera 1 mm away only (too little parallax).
    views[1] = views[1].subset(np.array([True, True, True, False]))
    views[2] = views[2].subset(np.array([False, False, False, True]))
    result = triangulate_tracks(views, len(pts), conf)
    assert result.status.tolist() == [TrackStatus.OK, TrackStatus.DEPTH,
                                      TrackStatus.REPROJECTION, TrackStatus.PARALLAX]
    assert result.kept[0].tolist() == [True, False, False, False]
    assert result.kept[1].tolist() == [True, False, False]
    assert np.linalg.norm(result.points_world[0] - pts[0]) < 1e-6


def test_a_bad_observation_is_dropped_when_enough_remain():
    pts = _points(10, seed=1)
    views = _views(PINHOLE, _poses([-0.25, 0.0, 0.25]), pts)
    views[2].pixels_px[4] += (0.0, 15.0)
    result = triangulate_tracks(views, len(pts), LOOSE)
    assert result.accepted.all()
    assert not result.kept[2][4] and result.kept[2].sum() == 9
    assert np.linalg.norm(result.points_world[4] - pts[4]) < 1e-6


def test_far_points_are_rejected_by_depth_range():
    pts = _points(5)
    pts[0] = (0.0, 300.0, 1.0)
    result = triangulate_tracks(_views(PINHOLE, _poses([0.0, 0.3]), pts), len(pts),
                                TriangulationConf(max_depth_m=50.0, min_parallax_deg=0.01,
                                                  max_depth_uncertainty=1.0))
    assert result.status[0] == TrackStatus.DEPTH
    assert result.accepted[1:].all()


def test_uncertain_points_are_rejected():
    """Same rays, coarser keypoints: the predicted depth uncertainty decides."""
    pts = _points(30, depth=(2.0, 2.2))
    fine = _views(PINHOLE, _poses([0.0, 0.4]), pts)
    # sigma_z ~ sqrt(2) z^2 sigma / (f b) = 1.41 * 4.4 * 0.5 / (250 * 0.4) = 3.1 cm (noise in
    # both views), 1.5 % of the range.
    expected = np.sqrt(2) * 4.4 * 0.5 / (250 * 0.4) / 2.1
    assert np.median(depth_uncertainty(pts, fine, 0.5)) == pytest.approx(expected, rel=0.2)
    conf = TriangulationConf(max_depth_uncertainty=0.02)
    assert triangulate_tracks(fine, len(pts), conf).accepted.all()
    coarse = [ViewObservations(v.camera, v.cam_from_world, v.point_index, v.pixels_px,
                               np.full(len(pts), 4.0)) for v in fine]
    assert (triangulate_tracks(coarse, len(pts), conf).status == TrackStatus.UNCERTAIN).all()


def test_conf_validation():
    with pytest.raises(ConfigError, match="ratio"):
        TriangulationConf(ratio=1.5)
    with pytest.raises(ConfigError, match="max_depth_m"):
        TriangulationConf(min_depth_m=2.0, max_depth_m=1.0)
    with pytest.raises(ConfigError, match="depth_interpolation"):
        TriangulationConf(depth_interpolation="cubic")


# -- depth ------------------------------------------------------------------------------------

def test_sample_depth_interpolates_and_rejects_discontinuities():
    depth = np.full((10, 10), 2.0, np.float32)
    depth[:, 5:] = 3.0                       # a step between columns 4 and 5
    depth[0, 0] = np.nan
    px = np.array([[2.5, 3.5], [4.5, 3.0], [0.2, 0.2], [9.5, 3.0], [7.0, 7.0]])
    z, valid = sample_depth(depth, px)
    assert valid.tolist() == [True, False, False, False, True]
    assert np.allclose(z[valid], [2.0, 3.0])
    ramp = np.add.outer(np.zeros(10), 2.0 + 0.01 * np.arange(10)).astype(np.float32)
    z, valid = sample_depth(ramp, np.array([[3.25, 4.0]]))
    assert valid[0] and z[0] == pytest.approx(2.0325, abs=1e-6)
    z, _ = sample_depth(ramp, np.array([[3.25, 4.0]]), interpolation="nearest")
    assert z[0] == pytest.approx(2.03, abs=1e-6)


def test_landmarks_from_depth_lie_on_the_surface(synthetic_scene_radtan):
    scene = synthetic_scene_radtan
    feats = extract(scene.keyframe_images[0], FeatureConf(max_features=500))
    kf = Keyframe(image=scene.keyframe_images[0], camera=scene.camera, features={"sift": feats},
                  id=0, world_from_cam=scene.keyframe_poses[0], depth=scene.keyframe_depths[0])
    idx, pts = landmarks_from_depth(kf, "sift")
    assert 0.8 * len(feats) < len(idx) <= len(feats)
    # Back into the image: the same pixels, at the rendered depth.
    p_cam = transform_points(invert(kf.world_from_cam), pts)
    assert np.allclose(scene.camera.project(p_cam), feats.keypoints_px[idx], atol=1e-6)
    z, _ = sample_depth(kf.depth, feats.keypoints_px[idx])
    assert np.allclose(p_cam[:, 2], z, atol=1e-5)
    # Keypoints on the panel's silhouette are refused (a depth discontinuity).
    rejected = np.setdiff1d(np.arange(len(feats)), idx)
    _, ok = sample_depth(kf.depth, feats.keypoints_px[rejected])
    assert not ok.any()
    no_depth = Keyframe(image=kf.image, camera=kf.camera, features=kf.features, id=0,
                        world_from_cam=kf.world_from_cam)
    assert len(landmarks_from_depth(no_depth, "sift")[0]) == 0


def test_lift_pixels_inverts_projection():
    pose = _poses([0.1])[0]
    pts = _points(20)
    p_cam = transform_points(invert(pose), pts)
    px = RADTAN.project(p_cam)
    assert np.allclose(lift_pixels(RADTAN, pose, px, p_cam[:, 2]), pts, atol=1e-9)


# -- keyframe-level triangulation -------------------------------------------------------------

def _map_with_keyframes(scene, ids, *, depth_for=()):
    kmap = KeyframeMap()
    for i in ids:
        feats = extract(scene.keyframe_images[i], FeatureConf(max_features=1000))
        kmap.add_keyframe(Keyframe(image=scene.keyframe_images[i], camera=scene.camera,
                                   features={"sift": feats}, id=i,
                                   world_from_cam=scene.keyframe_poses[i],
                                   depth=scene.keyframe_depths[i] if i in depth_for else None))
    return kmap


def _landmark_errors(scene, state):
    """Distance of each landmark to the rendered surface along its first observation's ray."""
    errors = []
    for lm in state.landmarks.values():
        kf_id, kind, idx = min(lm.observations)
        kf = state.keyframes[kf_id]
        px = kf.features[kind].keypoints_px[idx:idx + 1]
        z, ok = sample_depth(scene.keyframe_depths[kf_id], px)
        if ok[0]:
            truth = lift_pixels(kf.camera, kf.world_from_cam, px, z)[0]
            errors.append(np.linalg.norm(truth - lm.point_world))
    return np.array(errors)


def test_triangulate_keyframe_accuracy_and_track_extension(synthetic_scene):
    scene = synthetic_scene
    kmap = _map_with_keyframes(scene, [0, 1, 2])
    conf = TriangulationConf()
    first = triangulate_keyframe(kmap, 1, [0], "sift", conf)
    assert first.created > 100 and first.extended == 0
    count_after_two = len(kmap.snapshot().landmarks)
    second = triangulate_keyframe(kmap, 2, [0, 1], "sift", conf)
    state = kmap.snapshot()
    assert second.extended > 50           # matches to existing landmarks extend their tracks
    assert len(state.landmarks) == count_after_two + second.created
    three = [lm for lm in state.landmarks.values() if len(lm.observations) == 3]
    assert len(three) > 50
    for lm in state.landmarks.values():   # at most one keypoint per keyframe
        assert len({o[0] for o in lm.observations}) == len(lm.observations)
        for kf_id, kind, idx in lm.observations:
            kf = state.keyframes[kf_id]
            assert kf.features[kind].landmark_ids[idx] == lm.id
            assert np.array_equal(kf.features[kind].points_world[idx], lm.point_world)
            feats = kf.features[kind]
            p_cam = transform_points(invert(kf.world_from_cam), lm.point_world[None])
            px = kf.camera.project(p_cam)
            limit = conf.max_reprojection_px * keypoint_sigmas(feats)[idx]
            assert np.linalg.norm(px - feats.keypoints_px[idx]) <= limit + 1e-6
    errors = _landmark_errors(scene, state)
    assert np.median(errors) < 0.005
    assert np.mean(errors < 0.03) > 0.9


def test_triangulate_keyframe_from_depth_extends_and_creates(synthetic_scene):
    scene = synthetic_scene
    kmap = _map_with_keyframes(scene, [0, 1, 2], depth_for={2})
    triangulate_keyframe(kmap, 1, [0], "sift")
    before = set(kmap.snapshot().landmarks)
    stats = triangulate_keyframe(kmap, 2, [0, 1], "sift")
    assert stats.from_depth > 100 and stats.extended > 50 and stats.created == 0
    state = kmap.snapshot()
    new = [state.landmarks[i] for i in sorted(set(state.landmarks) - before)]
    assert len(new) == stats.from_depth
    kf = state.keyframes[2]
    feats = kf.features["sift"]
    for lm in new:                        # at the rendered depth of keyframe 2's keypoint
        idx = next(o[2] for o in lm.observations if o[0] == 2)
        z, ok = sample_depth(kf.depth, feats.keypoints_px[idx:idx + 1])
        assert ok[0]
        px = feats.keypoints_px[idx:idx + 1]
        assert np.allclose(lift_pixels(kf.camera, kf.world_from_cam, px, z)[0], lm.point_world,
                           atol=1e-9)
    # ... and the neighbours' free matches were attached to them where they reproject.
    assert sum(len(lm.observations) > 1 for lm in new) > 20
    assert np.median(_landmark_errors(scene, state)) < 0.005
    plain = triangulate_keyframe(_map_with_keyframes(scene, [0, 2], depth_for={2}), 2, [0],
                                 "sift", use_depth=False)
    assert plain.from_depth == 0 and plain.created > 0
