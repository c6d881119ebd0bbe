"""The stereo, rgbd and rotation synth presets: a two-camera rig with exact extrinsics, sensor-
like RGB-D depth next to exact truth depth, and cameras that (almost) only rotate. Small images
and few frames; trajectories are checked at full length without rendering."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from reloc_service.core.cameras import Camera
from reloc_service.core.geometry import invert, rotation_angle, transform_points
from reloc_service.tools.data.dataset import DatasetEntry, read_dataset
from reloc_service.tools.synth import PRESETS, render_dataset
from reloc_service.tools.synth.depth_sensor import sensor_depth
from reloc_service.tools.synth.presets import STEREO_BASELINE_M, DepthSensor
from reloc_service.tools.synth.renderer import render_frame
from reloc_service.tools.synth.scenes import build_scene
from reloc_service.tools.synth.trajectories import make_trajectories

SMALL_STEREO = dataclasses.replace(PRESETS["stereo"], n_map=2, n_query=1)
SMALL_RGBD = dataclasses.replace(PRESETS["rgbd"], n_map=2, n_query=1)


def _centres(poses: list[np.ndarray]) -> np.ndarray:
    return np.array([p[:3, 3] for p in poses])


def _yaw_deg(poses: list[np.ndarray]) -> np.ndarray:
    """Heading of each optical axis (world z up), degrees from +x towards +y."""
    axes = np.array([p[:3, 2] for p in poses])
    return np.degrees(np.arctan2(axes[:, 1], axes[:, 0]))


def _nearest_rotation_deg(poses: list[np.ndarray], others: list[np.ndarray]) -> np.ndarray:
    return np.array([min(np.degrees(rotation_angle(p[:3, :3].T @ o[:3, :3])) for o in others)
                     for p in poses])


def _sample(img: np.ndarray, px: np.ndarray) -> np.ndarray:
    return map_coordinates(img.astype(np.float64), [px[:, 1], px[:, 0]], order=1, mode="nearest")


# -- stereo ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def stereo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "stereo"
    return render_dataset(SMALL_STEREO, out, seed=0, workers=1, progress=False, scale=0.25)


def test_stereo_rig_has_two_cameras_011_m_apart_with_one_orientation(stereo: Path) -> None:
    data = read_dataset(stereo)
    assert set(data.cameras) == {"cam0", "cam1"}
    assert data.cameras["cam1"] == PRESETS["stereo"].rig[0].camera.scaled(0.25)
    assert data.cameras["cam0"].size == data.cameras["cam1"].size == (188, 120)
    assert [(e.camera_id, e.image_path) for e in data.map_entries] == [
        ("cam0", "images/map/cam0/000000.png"), ("cam1", "images/map/cam1/000000.png"),
        ("cam0", "images/map/cam0/000001.png"), ("cam1", "images/map/cam1/000001.png")]
    for left, right in zip(data.map_entries[::2], data.map_entries[1::2], strict=True):
        cam0_from_cam1 = invert(left.world_from_cam) @ right.world_from_cam
        np.testing.assert_allclose(cam0_from_cam1[:3, :3], np.eye(3), atol=1e-12)
        np.testing.assert_allclose(cam0_from_cam1[:3, 3], [STEREO_BASELINE_M, 0, 0], atol=1e-9)
    assert [e.camera_id for e in data.query_entries] == ["cam0"]
    # exact depth is ground truth for scoring only: a stereo rig has no depth sensor
    assert data.depth == {} and not (stereo / "depth.txt").exists()
    assert set(data.truth_depth) == {e.image_path for e in data.map_entries + data.query_entries}


def _stereo_check(data, a: DatasetEntry, b: DatasetEntry) -> tuple[float, float]:
    """Lift a's pixels with a's truth depth, project into b through b's own camera: median
    |I_a - I_b| at unoccluded landings, and the same for a 6-15 px wrong landing."""
    cam_a, cam_b = data.camera(a), data.camera(b)
    img_a, img_b = data.load_image(a).astype(np.float64), data.load_image(b).astype(np.float64)
    depth_a, depth_b = data.load_truth_depth(a), data.load_truth_depth(b)
    v, u = np.nonzero(np.isfinite(depth_a))
    rays = cam_a.unproject(np.column_stack([u, v]).astype(np.float64))
    p_b = transform_points(invert(b.world_from_cam) @ a.world_from_cam,
                           rays / rays[:, 2:] * depth_a[v, u][:, None])
    px = cam_b.project(p_b)
    ok = cam_b.in_image(px, margin=2.0)
    ok[ok] &= np.abs(_sample(np.nan_to_num(depth_b), px[ok]) - p_b[ok, 2]) < 0.02
    shift = np.random.default_rng(0).uniform(6, 15, (ok.sum(), 2)) * np.random.default_rng(
        1).choice([-1, 1], (ok.sum(), 2))
    return (float(np.median(np.abs(img_a[v[ok], u[ok]] - _sample(img_b, px[ok])))),
            float(np.median(np.abs(img_a[v[ok], u[ok]] - _sample(img_b, px[ok] + shift)))))


def test_stereo_pair_agrees_photometrically_through_each_camera_model(stereo: Path) -> None:
    data = read_dataset(stereo)
    left, right = data.map_entries[0], data.map_entries[1]
    diff, wrong = _stereo_check(data, left, right)
    assert diff < 5.0 and diff < 0.3 * wrong, (diff, wrong)
    swapped = dataclasses.replace(right, camera_id="cam0")  # the other lens: worse
    worse, _ = _stereo_check(data, left, swapped)
    assert worse > diff
    median = float(np.nanmedian(data.load_truth_depth(left)))
    assert 2.3 < median < 4.0, f"median depth {median:.2f} m: the far end of the room"


def test_stereo_path_is_vio_like_and_queries_revisit_it() -> None:
    preset = PRESETS["stereo"]
    assert 12 <= preset.n_map <= 16 and preset.n_map_frames == 2 * preset.n_map
    assert 15 <= preset.n_query <= 25
    rig, queries = make_trajectories(preset.trajectory, preset.n_map, preset.n_query, seed=0)
    steps = np.linalg.norm(np.diff(_centres(rig), axis=0), axis=1)
    assert 0.1 < np.median(steps) < 0.35 and steps.max() < 0.5
    gaps = [np.min(np.linalg.norm(_centres(rig) - c, axis=1)) for c in _centres(queries)]
    assert 0.03 < np.median(gaps) and max(gaps) < 0.5
    assert _nearest_rotation_deg(queries, rig).max() < 20.0
    assert np.all(np.abs(_yaw_deg(rig + queries)) < 35.0)  # looking down the room (+x)


# -- rgbd ------------------------------------------------------------------------------------

def _two_level_scene(shape: tuple[int, int] = (480, 640)) -> tuple[np.ndarray, np.ndarray]:
    """A 2 m wall with a 1 m box in front, a 5 m far region, a 0.3 m near region and a grazing
    strip (cosine of incidence 0.1), as depth and cos(incidence) images."""
    depth = np.full(shape, 2.0, np.float32)
    depth[150:300, 200:400] = 1.0
    depth[:, 560:] = 5.0
    depth[:40, :200] = 0.3
    cos = np.full(shape, 0.9, np.float32)
    cos[400:, :200] = 0.1
    return depth, cos


def test_sensor_depth_noise_and_holes_follow_the_model() -> None:
    depth, cos = _two_level_scene()
    sensor = DepthSensor()
    out = sensor_depth(depth, cos, sensor, np.random.default_rng(0))
    assert np.array_equal(out, sensor_depth(depth, cos, sensor, np.random.default_rng(0)))
    assert np.all(out[:, 562:] == 0) and np.all(out[:38, :198] == 0)  # out of range
    assert np.all(out[402:, :198] == 0)  # grazing incidence
    assert np.all(out[148:152, 210:390] == 0) and np.all(out[200:250, 198:202] == 0)  # edges
    assert np.any(out[145:147, 210:390] > 0)  # the band is a few pixels, not more
    inner_box, inner_wall = out[160:290, 210:390], out[60:140, 220:540]
    for region, z in ((inner_box, 1.0), (inner_wall, 2.0)):
        valid = region > 0
        assert 0.98 < valid.mean() < 1.0  # ~0.5 % random dropouts
        sigma = sensor.axial_noise_per_m2 * z * z
        assert np.std(region[valid] - z) == pytest.approx(sigma, rel=0.06)
        assert np.abs(region[valid] - z).max() < 5.5 * sigma


def test_rgbd_depth_txt_is_sensor_like_and_truth_depth_is_exact(tmp_path: Path) -> None:
    out = render_dataset(SMALL_RGBD, tmp_path / "rgbd", seed=0, workers=1, progress=False,
                         scale=0.5)
    data = read_dataset(out)
    assert data.cameras["cam0"].model == "pinhole" and data.cameras["cam0"].fx == 262.5
    every = {e.image_path for e in data.map_entries + data.query_entries}
    assert set(data.depth) == set(data.truth_depth) == every
    assert all(mpu == 0.001 for _, mpu in data.depth.values())
    k = PRESETS["rgbd"].depth_sensor.axial_noise_per_m2
    for entry in data.map_entries + data.query_entries:
        truth, sensed = data.load_truth_depth(entry), data.load_depth(entry)
        assert truth is not None and sensed is not None
        both = np.isfinite(truth) & np.isfinite(sensed)
        holes = np.isfinite(truth) & ~np.isfinite(sensed)
        assert 0.005 < holes.mean() < 0.3, f"{entry.image_path}: {holes.mean():.3f} holes"
        assert not np.any(np.isfinite(sensed) & ((truth > 4.5) | (truth < 0.5)))
        assert not np.array_equal(truth[both], sensed[both])
        sigma = k * truth[both] ** 2
        normalised = (sensed[both] - truth[both]) / sigma
        # 1 mm quantisation of both adds (1 mm)^2 / 6 of variance: ~2 % at 1.3 m
        assert 0.9 < np.std(normalised) < 1.15 and abs(np.mean(normalised)) < 0.1
        assert np.all(np.abs(sensed[both] - truth[both]) < 5.5 * sigma + 1e-3)


# -- rotation --------------------------------------------------------------------------------

@pytest.mark.parametrize(("name", "spread", "query_reach"), [
    ("rotation", (0.0, 0.01), 0.03), ("rotation-baseline", (0.03, 0.05), 0.05)])
def test_rotation_keyframes_only_rotate_and_queries_stay_there(
        name: str, spread: tuple[float, float], query_reach: float) -> None:
    preset = PRESETS[name]
    assert 10 <= preset.n_map <= 16 and 10 <= preset.n_query <= 15
    assert preset.camera == PRESETS["room"].camera and preset.scene == "room"
    for seed in (0, 1, 2):
        keyframes, queries = make_trajectories(preset.trajectory, preset.n_map, preset.n_query,
                                               seed)
        centres = _centres(keyframes)
        centre = centres.mean(axis=0)
        extent = np.linalg.norm(centres[:, None] - centres[None], axis=2).max()
        if name == "rotation":
            assert np.linalg.norm(centres - centre, axis=1).max() < 0.01
        assert spread[0] <= extent <= spread[1], f"keyframe centres span {extent:.3f} m"
        assert np.linalg.norm(_centres(queries) - centre, axis=1).max() < query_reach
        yaw = np.unwrap(np.radians(_yaw_deg(keyframes)))
        assert 110 < np.degrees(np.ptp(yaw)) < 130
        pitch = np.degrees(np.arcsin(np.array([k[2, 2] for k in keyframes])))
        assert np.ptp(pitch) > 4.0  # not a planar sweep
        query_yaw = np.degrees(np.unwrap(np.radians(_yaw_deg(queries)), period=2 * np.pi))
        assert np.all((query_yaw > np.degrees(yaw.min()) - 12)
                      & (query_yaw < np.degrees(yaw.max()) + 12))
        assert _nearest_rotation_deg(queries, keyframes).min() > 0.5  # new orientations


def test_rotation_views_see_walls_15_to_4_m_away() -> None:
    preset = PRESETS["rotation"]
    scene = build_scene(preset.scene, 0)
    keyframes, _ = make_trajectories(preset.trajectory, preset.n_map, preset.n_query, 0)
    camera: Camera = preset.camera.scaled(0.1)
    for pose in keyframes[::4]:
        depth = render_frame(scene, camera, pose, rng=np.random.default_rng(0),
                             supersample=1).depth
        assert 1.5 < np.median(depth[depth > 0]) < 4.0


def test_rig_and_sensor_presets_are_listed(capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from reloc_service.tools.synth.cli import add_synth_arguments, main_synth

    parser = argparse.ArgumentParser()
    add_synth_arguments(parser)
    assert main_synth(parser.parse_args(["--list"])) == 0
    listing = capsys.readouterr().out
    for name in ("stereo", "rgbd", "rotation", "rotation-baseline"):
        assert name in listing
    assert " 28 map " in listing  # the stereo preset counts both cameras' keyframes
