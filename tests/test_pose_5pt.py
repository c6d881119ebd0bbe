"""The five-point pose finder (``5pt``): poses from keyframes without landmarks (a pure
rotation map, a tiny-baseline map) in the rendered room of conftest.py, honest covariances,
refusals, and the registry."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from conftest import PINHOLE, render_view, room_planes

from reloc_service.algorithms.place.base import PlaceCandidate
from reloc_service.algorithms.pose.base import create_pose_finder
from reloc_service.algorithms.relocalizers.base import VerifyConf, position_sigma_m, verify
from reloc_service.algorithms.relocalizers.factory import create_relocalizer, list_methods
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import ConfigError
from reloc_service.core.features import extract
from reloc_service.core.frame import Features, Frame, Keyframe
from reloc_service.core.geometry import invert, look_at, pose_error, se3_log, so3_exp, transform_points
from reloc_service.core.map import KeyframeMap
from reloc_service.engine import Engine, EngineConf

CENTRE = np.array([0.0, 0.3, 1.2])
#: Distance from CENTRE to the farthest corner of the room (x +-1.8, y -1..2.5, z 0..2.6): a
#: true upper bound of the scene's distance, as a user would give it for a room.
FARTHEST_M = float(max(np.linalg.norm(np.array(c) - CENTRE)
                       for c in itertools.product((-1.8, 1.8), (-1.0, 2.5), (0.0, 2.6))))


def view(centre: np.ndarray, yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0
         ) -> np.ndarray:
    """``world_from_cam`` at ``centre`` looking along yaw (from +y towards +x) and pitch."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    pose = look_at(centre, centre + [np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch),
                                     np.sin(pitch)])
    pose[:3, :3] = pose[:3, :3] @ so3_exp([0.0, 0.0, np.radians(roll_deg)])
    return pose


def render(world_from_cam: np.ndarray) -> np.ndarray:
    return render_view(room_planes(), PINHOLE, world_from_cam)[0]


ROTATION_KEYFRAMES = [view(CENTRE, yaw) for yaw in (-50, -25, 0, 25, 50)]
ROTATION_QUERIES = [view(CENTRE, 12, 5, 8), view(CENTRE, -35, -6, -5), view(CENTRE, 40, 3, 0)]
# Keyframes 3.6-4.6 cm apart; queries 3-5 cm from them.
TINY_KEYFRAMES = [view(CENTRE + offset, yaw) for offset, yaw in
                  zip([(-0.02, 0, 0), (0.02, 0, 0), (0, 0, 0.035), (0, 0.03, 0)], (-10, 5, 15, -20),
                      strict=True)]
TINY_QUERIES = [view(CENTRE + [0.03, -0.02, 0.02], 0, 4, 5),
                view(CENTRE + [-0.03, 0.03, 0.0], -15, -3, 0),
                view(CENTRE + [0.0, 0.04, 0.03], 10, 0, -5)]


@pytest.fixture(scope="module")
def rotation_engine() -> Engine:
    """The map builder on keyframes sharing one centre (nothing to triangulate)."""
    engine = Engine(EngineConf(methods=("sbi+5pt", "sbi+p3p"),
                               options={"5pt": {"assumed_depth_m": FARTHEST_M}}))
    for i, pose in enumerate(ROTATION_KEYFRAMES):
        engine.add_keyframe(i, render(pose), PINHOLE, pose)
    return engine


@pytest.fixture(scope="module")
def tiny_map() -> KeyframeMap:
    """Keyframes a few cm apart with SIFT features and no landmark at all."""
    kmap = KeyframeMap()
    for i, pose in enumerate(TINY_KEYFRAMES):
        image = render(pose)
        kmap.add_keyframe(Keyframe(image=image, camera=PINHOLE, features={"sift": extract(image)},
                                   id=i, world_from_cam=pose))
    return kmap


@pytest.mark.parametrize("index", range(len(ROTATION_QUERIES)))
def test_pure_rotation_map_is_served_where_p3p_cannot(rotation_engine, index):
    gt = ROTATION_QUERIES[index]
    assert rotation_engine.map.snapshot().landmark_count() == 0
    result = rotation_engine.relocalize(Frame(render(gt), PINHOLE), method="sbi+5pt")
    assert result.ok, result.reason
    dt, dr = pose_error(result.world_from_cam, gt)
    assert dt < 0.25 and np.degrees(dr) < 10
    assert len(result.matched_keyframe_ids) >= 2
    # The position comes from the bound on undetectable parallax: cm, not mm, not unbounded.
    assert 0.005 < position_sigma_m(result.covariance) < VerifyConf().max_position_sigma_m
    assert {"features", "match", "solve", "verify"} <= result.timings.keys()
    p3p = rotation_engine.relocalize(Frame(render(gt), PINHOLE), method="sbi+p3p")
    assert not p3p.ok


def test_rotation_without_a_scene_distance_gives_no_position(rotation_engine):
    reloc = create_relocalizer("sbi+5pt", rotation_engine.map)  # no assumed_depth_m
    query = Frame(render(ROTATION_QUERIES[0]), PINHOLE)
    result = reloc.relocalize(query)
    assert not result.ok and "position too uncertain" in result.reason
    candidates = [PlaceCandidate(i, 1.0) for i in range(len(ROTATION_KEYFRAMES))]
    est = reloc.pose.find_pose(query, candidates, rotation_engine.map.snapshot())
    assert np.degrees(pose_error(est.world_from_cam, ROTATION_QUERIES[0])[1]) < 1.0
    assert position_sigma_m(est.covariance) == np.inf


@pytest.mark.parametrize("index", range(len(TINY_QUERIES)))
def test_tiny_baseline_map_without_landmarks(tiny_map, index):
    gt = TINY_QUERIES[index]
    result = create_relocalizer("sbi+5pt", tiny_map).relocalize(Frame(render(gt), PINHOLE))
    assert result.ok, result.reason
    dt, dr = pose_error(result.world_from_cam, gt)
    assert dt < 0.25 and np.degrees(dr) < 10
    assert len(result.matched_keyframe_ids) >= 2 and result.reprojection_rms_px < 1.0
    assert not create_relocalizer("sbi+p3p", tiny_map).relocalize(Frame(render(gt), PINHOLE)).ok


def test_one_keyframe_gives_no_scale(tiny_map):
    finder = create_pose_finder({"name": "5pt"})
    est = finder.find_pose(Frame(render(TINY_QUERIES[0]), PINHOLE), [PlaceCandidate(0, 1.0)],
                           tiny_map.snapshot())
    assert est is not None and est.inliers > 50
    ok, reason, _ = verify(est, VerifyConf())
    assert not ok and "position too uncertain" in reason


def unrelated_images() -> list[np.ndarray]:
    import skimage.data as data

    noise = np.random.default_rng(0).integers(0, 256, (PINHOLE.height, PINHOLE.width))
    return [cv2.resize(data.coins(), PINHOLE.size),                  # another scene
            cv2.GaussianBlur(noise.astype(np.uint8), (0, 0), 1.5),     # random texture
            render(view(CENTRE, 180))]                                 # the room behind the map


@pytest.mark.parametrize("index", range(3))
def test_unrelated_queries_are_refused(tiny_map, rotation_engine, index):
    image = unrelated_images()[index]
    assert not create_relocalizer("sbi+5pt", tiny_map).relocalize(Frame(image, PINHOLE)).ok
    assert not rotation_engine.relocalize(Frame(image, PINHOLE), method="sbi+5pt").ok


def test_registry_and_options():
    methods = {m["method"] for m in list_methods()}
    assert {"sbi+5pt", "bow+5pt"} <= methods
    with pytest.raises(ConfigError, match="unknown option"):
        create_pose_finder({"name": "5pt", "threshold": 2.0})
    with pytest.raises(ConfigError, match="unknown option"):
        create_relocalizer("sbi+5pt", KeyframeMap(), options={"5pt": {"nope": 1}})
    with pytest.raises(ConfigError):
        create_pose_finder({"name": "5pt", "assumed_depth_m": -1.0})
    reloc = create_relocalizer("sbi+5pt", KeyframeMap(), options={"multi": {"num_candidates": 4}})
    assert reloc.group_size == 4 and reloc.required_features == {"sift"}


# -- statistics on exact synthetic correspondences (no rendering) ------------------------------
CAMERA = PinholeCamera(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)


def synthetic_frame(points: np.ndarray, descriptors: np.ndarray, world_from_cam: np.ndarray,
                    noise_px: float, rng: np.random.Generator, keyframe_id: int | None = None
                    ) -> Frame:
    """A frame whose SIFT features are the points' projections (with noise) and descriptors."""
    points_cam = transform_points(invert(world_from_cam), points)
    px = CAMERA.project(points_cam) + rng.normal(0.0, noise_px, (len(points), 2))
    seen = CAMERA.in_image(px) & (points_cam[:, 2] > 0)
    feats = {"sift": Features.create("sift", px[seen], descriptors[seen])}
    image = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
    if keyframe_id is None:
        return Frame(image, CAMERA, features=feats)
    return Keyframe(image=image, camera=CAMERA, features=feats, id=keyframe_id,
                    world_from_cam=world_from_cam)


@pytest.mark.parametrize("rotation", [False, True])
def test_covariance_matches_the_errors(rotation):
    """Over noisy trials the Mahalanobis distance of the true pose averages the 6 degrees of
    freedom (general motion); a pure rotation's covariance is a bound: larger, never smaller."""
    rng = np.random.default_rng(1)
    points = rng.uniform([-3, -2, 3], [3, 2, 8], (400, 3))
    descriptors = rng.normal(size=(400, 128)).astype(np.float32)
    up = [0, -1, 0]
    if rotation:
        keyframes = [look_at([0, 0, 0], [-1, 0, 5], up), look_at([0, 0, 0], [1, 0.3, 5], up)]
        gt = look_at([0, 0, 0], [0.2, 0, 5], up)
    else:
        keyframes = [look_at([-0.5, 0, 0], [0, 0, 5], up), look_at([0.5, 0.1, 0], [0, 0, 5], up)]
        gt = look_at([0.1, 0.3, 0.5], [0.2, 0, 5], up)
    finder = create_pose_finder({"name": "5pt", "keypoint_sigma_px": 0.5, "assumed_depth_m": 8.0})
    mahalanobis = []
    for _ in range(20):
        kmap = KeyframeMap()
        for i, pose in enumerate(keyframes):
            kmap.add_keyframe(synthetic_frame(points, descriptors, pose, 0.5, rng, i))
        query = synthetic_frame(points, descriptors, gt, 0.5, rng)
        est = finder.find_pose(query, [PlaceCandidate(0, 1.0), PlaceCandidate(1, 1.0)],
                               kmap.snapshot())
        assert verify(est, VerifyConf())[0]
        xi = se3_log(invert(est.world_from_cam) @ gt)
        mahalanobis.append(xi @ np.linalg.solve(est.covariance, xi))
    if rotation:
        assert np.mean(mahalanobis) < 3.0
    else:
        assert 3.0 < np.mean(mahalanobis) < 10.0
