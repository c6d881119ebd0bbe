"""Synthetic dataset generator: exact ray casting, ground-truth consistency (depth, poses and
lens distortion agree), determinism per seed, presets and hard variants. Tiny images only."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from reloc_service.core.cameras import Camera, PinholeCamera
from reloc_service.core.errors import ConfigError, DatasetError
from reloc_service.core.geometry import check_pose, invert, transform_points
from reloc_service.tools.data.dataset import DatasetEntry, read_dataset
from reloc_service.tools.synth import PRESETS, render_dataset
from reloc_service.tools.synth.cli import add_synth_arguments, main_synth
from reloc_service.tools.synth.presets import get_preset
from reloc_service.tools.synth.renderer import (
    cast_rays,
    draw_nuisance,
    make_ray_grid,
    motion_blur,
    render_frame,
)
from reloc_service.tools.synth.scene import (
    DESK_FURNITURE,
    ROOM_FURNITURE,
    ROOM_SIZE,
    Lighting,
    Scene,
    Texture,
    facing_quad,
)
from reloc_service.tools.synth.scenes import build_scene
from reloc_service.tools.synth.trajectories import make_trajectories

SCALE = 0.25  # 160 x 120 images: fast, still enough texture for photometric checks
SMALL_DESK = dataclasses.replace(PRESETS["desk"], n_map=3, n_query=2)
SMALL_DESK_HARD = dataclasses.replace(PRESETS["desk-hard"], n_map=3, n_query=2)


def _files(root: Path, sub: str) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted((root / sub).rglob("*.png"))}


@pytest.fixture(scope="module")
def desk(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "desk"
    return render_dataset(SMALL_DESK, out, seed=0, workers=2, progress=False, scale=SCALE)


@pytest.fixture(scope="module")
def desk_scene() -> Scene:
    return build_scene("desk", 0)


# -- the ray caster against closed-form answers ---------------------------------------------

def _one_quad_scene(z: float) -> Scene:
    """A 1 x 0.5 m quad at depth z facing a camera at the origin looking along +z."""
    tex = Texture.from_image(np.full((50, 100), 0.5, dtype=np.float32), 0.01)
    quad = facing_quad((0.2, 0.1, z), (0, 0, -1), (0, -1, 0), (1.0, 0.5), 0)
    return Scene.from_quads("test", [quad], [tex], Lighting())


def test_cast_rays_hits_exactly_the_projected_rectangle() -> None:
    cam = PinholeCamera(64, 48, fx=40.0, fy=40.0, cx=31.5, cy=23.5)
    grid = make_ray_grid(cam, tile=16)
    hits = cast_rays(_one_quad_scene(2.0), np.eye(4), grid)
    depth = grid.to_image(np.where(np.isfinite(hits.t), hits.t * grid.rays[2], 0))
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    x, y = (u - 31.5) / 40.0 * 2.0, (v - 23.5) / 40.0 * 2.0  # the pixel's point on z = 2
    inside = (np.abs(x - 0.2) < 0.5) & (np.abs(y - 0.1) < 0.25)
    border = (np.abs(np.abs(x - 0.2) - 0.5) < 0.03) | (np.abs(np.abs(y - 0.1) - 0.25) < 0.03)
    assert np.array_equal((depth > 0)[~border], inside[~border])
    np.testing.assert_allclose(depth[inside], 2.0, rtol=1e-6)


def test_back_faces_and_points_behind_the_camera_are_not_drawn() -> None:
    cam = PinholeCamera(32, 24, fx=20.0, fy=20.0, cx=15.5, cy=11.5)
    grid = make_ray_grid(cam, tile=8)
    behind = cast_rays(_one_quad_scene(-2.0), np.eye(4), grid)
    assert np.all(behind.quad == -1)
    turned = np.diag([1.0, -1.0, -1.0, 1.0])  # camera looking along -z sees the back face
    scene = _one_quad_scene(-2.0)
    assert np.all(cast_rays(scene, turned, grid).quad == -1)


def test_motion_blur_kernel_preserves_brightness() -> None:
    img = np.zeros((41, 41), dtype=np.float32)
    img[20, 20] = 1.0
    out = motion_blur(img, 9.0, 0.0)
    assert out.sum() == pytest.approx(1.0, abs=1e-5)
    row_spread = np.flatnonzero(out[20] > 1e-3)
    assert 7 <= np.ptp(row_spread) + 1 <= 11 and out[:18].sum() < 1e-3  # horizontal line


# -- ground truth: depth, poses and distortion agree ----------------------------------------

def _bilinear(img: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Sample ``img`` at (N, 2) pixels (x, y) bilinearly: SciPy, independent of the renderer."""
    return map_coordinates(img.astype(np.float64), [px[:, 1], px[:, 0]], order=1,
                           mode="nearest")


def _depth(root: Path, entry_path: str) -> np.ndarray:
    raw = cv2.imread(str(root / entry_path.replace("images/", "truth_depth/")),
                     cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16
    return raw.astype(np.float64) * 0.001


def test_rendered_depth_agrees_with_scene_points_in_two_frames(desk: Path,
                                                                desk_scene: Scene) -> None:
    data = read_dataset(desk)
    cam = data.cameras["cam0"]
    points, normals = desk_scene.surface_points(np.random.default_rng(0), 40000)
    agree = np.ones(len(points), dtype=bool)
    see_through = np.zeros(len(points), dtype=bool)
    for entry in data.map_entries[:2]:
        world_from_cam = entry.world_from_cam
        p_cam = transform_points(invert(world_from_cam), points)
        facing = np.einsum("ij,ij->i", normals, world_from_cam[:3, 3] - points) > 0
        px = cam.project(p_cam)
        ok = facing & cam.in_image(px, margin=1.0) & (p_cam[:, 2] > 0.05)
        depth = _depth(desk, entry.image_path)
        rendered, nearest_around = np.zeros(len(points)), np.zeros(len(points))
        rendered[ok] = _bilinear(depth, px[ok])
        x0, y0 = np.floor(px[ok]).astype(int).T
        nearest_around[ok] = np.minimum.reduce([depth[y0 + dy, x0 + dx]
                                                for dy in (0, 1) for dx in (0, 1)])
        agree &= ok & (np.abs(rendered - p_cam[:, 2]) < 0.01)
        # impossible: all four pixels around a point facing the camera show what is behind it
        see_through |= ok & (nearest_around > p_cam[:, 2] + 0.02)
    seen = int(agree.sum())
    print(f"{seen} points seen by both frames, {see_through.mean():.4f} see-through")
    assert seen > 400, f"only {seen} scene points seen by both frames"
    assert see_through.sum() == 0


def _reprojection_check(root: Path, cam: Camera, a: DatasetEntry,
                        b: DatasetEntry) -> tuple[float, float, float]:
    """Lift every pixel of a with its depth, reproject into b through ``cam``: (fraction that
    lands in b unoccluded, median |I_a - I_b| there, the same for a random 6-15 px shift)."""
    img_a, img_b = (np.asarray(cv2.imread(str(root / e.image_path), 0), dtype=np.float64)
                    for e in (a, b))
    depth_a, depth_b = _depth(root, a.image_path), _depth(root, b.image_path)
    v, u = np.nonzero(depth_a > 0)
    rays = cam.unproject(np.column_stack([u, v]).astype(np.float64))
    p_a = rays / rays[:, 2:] * depth_a[v, u][:, None]  # Z-depth -> point in camera a
    p_b = transform_points(invert(b.world_from_cam) @ a.world_from_cam, p_a)
    px_b = cam.project(p_b)
    ok = cam.in_image(px_b, margin=2.0)
    ok[ok] &= np.abs(_bilinear(depth_b, px_b[ok]) - p_b[ok, 2]) < 0.01  # not occluded in b
    intensity_a = img_a[v[ok], u[ok]]
    shift = np.random.default_rng(0).uniform(6, 15, size=(ok.sum(), 2)) * \
        np.random.default_rng(1).choice([-1, 1], size=(ok.sum(), 2))
    return (float(ok.mean()), float(np.median(np.abs(intensity_a - _bilinear(img_b, px_b[ok])))),
            float(np.median(np.abs(intensity_a - _bilinear(img_b, px_b[ok] + shift)))))


def test_pixels_reprojected_with_depth_land_on_the_same_intensities(desk: Path) -> None:
    data = read_dataset(desk)
    cam = data.cameras["cam0"]
    a, b = data.map_entries[0], data.map_entries[1]
    overlap, diff, baseline = _reprojection_check(desk, cam, a, b)
    assert overlap > 0.45, "frames 0 and 1 should overlap"
    assert diff < 4.5 and diff < 0.25 * baseline
    # negative control: ignoring the lens distortion, most reprojections miss the surface
    pinhole = PinholeCamera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    overlap_pinhole, _, _ = _reprojection_check(desk, pinhole, a, b)
    assert overlap_pinhole < 0.7 * overlap


def test_dataset_files_and_metadata(desk: Path) -> None:
    data = read_dataset(desk)
    cam = data.cameras["cam0"]
    assert cam.model == "radtan" and (cam.width, cam.height) == (160, 120)
    assert len(data.map_entries) == 3 and len(data.query_entries) == 2
    # a monocular preset: exact depth for scoring only, no sensor depth for the map builder
    assert data.depth == {} and not (desk / "depth.txt").exists()
    # rendered through the very cameras it writes: their calibration is stated exact
    assert data.calibration_sigma == (0.0, 0.0)
    for entry in data.map_entries + data.query_entries:
        assert data.load_image(entry).shape == (120, 160)
        assert data.load_depth(entry) is None
        depth = data.load_truth_depth(entry)
        assert depth is not None and np.nanmin(depth) > 0.3 and np.nanmax(depth) < 6.0
    assert data.map_entries[0].image_path == "images/map/000000.png"
    meta = json.loads((desk / "synth.json").read_text())
    assert meta["preset"] == "desk" and meta["seed"] == 0 and meta["scale"] == SCALE


# -- determinism ----------------------------------------------------------------------------

def test_same_seed_gives_identical_files_with_any_worker_count(desk: Path,
                                                               tmp_path: Path) -> None:
    again = render_dataset(SMALL_DESK, tmp_path / "again", seed=0, workers=1, progress=False,
                           scale=SCALE)  # the fixture used a pool of 2
    for sub in ("images", "truth_depth"):
        assert _files(desk, sub) == _files(again, sub)
    for name in ("map.txt", "queries.txt", "cameras.json", "synth.json", "truth_depth.txt"):
        assert (desk / name).read_bytes() == (again / name).read_bytes()


def test_different_seeds_differ(desk: Path, tmp_path: Path) -> None:
    other = render_dataset(SMALL_DESK, tmp_path / "other", seed=1, workers=1, progress=False,
                           scale=SCALE)
    mine, theirs = _files(desk, "images"), _files(other, "images")
    assert mine.keys() == theirs.keys()
    assert all(mine[k] != theirs[k] for k in mine)
    assert (desk / "map.txt").read_text() != (other / "map.txt").read_text()


def test_hard_variant_changes_the_queries_only(desk: Path, tmp_path: Path) -> None:
    hard = render_dataset(SMALL_DESK_HARD, tmp_path / "hard", seed=0, workers=1,
                          progress=False, scale=SCALE)
    easy_images, hard_images = _files(desk, "images"), _files(hard, "images")
    maps = [k for k in easy_images if k.startswith("images/map/")]
    queries = [k for k in easy_images if k.startswith("images/query/")]
    assert all(easy_images[k] == hard_images[k] for k in maps)
    nuisances = json.loads((hard / "synth.json").read_text())["query_nuisances"]
    assert sorted(nuisances) == queries
    for k in queries:
        n = nuisances[k]
        if n["occluded"] or n["blur_px"] > 0 or n["gain"] != 1.0:
            assert easy_images[k] != hard_images[k], k
    assert (desk / "queries.txt").read_text() == (hard / "queries.txt").read_text()


# -- occluders, presets, trajectories, CLI --------------------------------------------------

def test_occluder_covers_about_a_quarter_of_the_query(desk_scene: Scene) -> None:
    preset = PRESETS["desk-hard"]
    cam = preset.camera.scaled(SCALE)
    _, queries = make_trajectories("desk", 3, 4, seed=0)
    assert preset.degradation is not None
    conf = dataclasses.replace(preset.degradation, occlusion_prob=1.0)
    for i, pose in enumerate(queries):
        nuisance = draw_nuisance(np.random.default_rng(i), conf, cam, pose,
                                 desk_scene.occluder_textures)
        depth = render_frame(desk_scene, cam, pose, rng=np.random.default_rng(0),
                             nuisance=nuisance).depth
        near = np.mean((depth > 0) & (depth <= conf.occluder_depth_m[1] + 1e-3))
        assert 0.14 < near < 0.36, f"query {i}: occluder covers {near:.0%}"


def test_presets_match_the_thesis_datasets() -> None:
    assert {"desk", "desk-hard", "room", "room-hard", "room-fov"} <= set(PRESETS)
    assert (PRESETS["desk"].n_map, PRESETS["desk"].n_query) == (10, 10)
    assert (PRESETS["room"].n_map, PRESETS["room"].n_query) == (84, 69)
    for name in ("desk", "room"):
        cam = PRESETS[name].camera
        assert cam.model == "radtan" and (cam.width, cam.height) == (640, 480)
        assert PRESETS[name].degradation is None
        assert PRESETS[name + "-hard"].degradation is not None
        assert PRESETS[name + "-hard"].camera == cam
    assert PRESETS["room-fov"].camera.model == "fov"
    with pytest.raises(ConfigError, match="room"):
        get_preset("nope")


@pytest.mark.parametrize("name", ["room", "desk"])
def test_laps_are_deterministic_offset_and_in_free_space(name: str) -> None:
    train, test = make_trajectories(name, 84, 69, seed=3)
    again, _ = make_trajectories(name, 84, 69, seed=3)
    assert all(np.array_equal(p, q) for p, q in zip(train, again, strict=True))
    assert not np.allclose(train[0], make_trajectories(name, 84, 69, seed=4)[0][0])
    centres = np.array([p[:3, 3] for p in train])
    gaps = [np.min(np.linalg.norm(centres - q[:3, 3], axis=1)) for q in test]
    assert 0.05 < np.median(gaps) < 0.5  # tens of centimetres off the training lap
    boxes = ROOM_FURNITURE if name == "room" else DESK_FURNITURE
    for pose in train + test:
        check_pose(pose)
        roll = np.degrees(np.arcsin(-pose[2, 0]))  # camera x axis leaving the horizontal
        assert abs(roll) < 6.0
        c = pose[:3, 3]
        assert not any(abs(c[0] - b.x) < b.dx and abs(c[1] - b.y) < b.dy
                       and c[2] < b.z0 + b.dz + 0.1 for b in boxes)
        if name == "room":
            assert np.all(c > 0.8) and np.all(c < np.array(ROOM_SIZE) - 0.8)
    rot_train = np.array([p[:3, :3] for p in train])
    cos_gap = [(np.einsum("kij,ij->k", rot_train, q[:3, :3]).max() - 1) / 2 for q in test]
    assert np.degrees(np.arccos(np.min(cos_gap))) < 35.0  # trace(Ra^T Rb) = 1 + 2 cos


def test_room_fov_renders_through_the_fov_model(tmp_path: Path) -> None:
    preset = dataclasses.replace(PRESETS["room-fov"], n_map=1, n_query=1)
    out = render_dataset(preset, tmp_path / "fov", seed=0, workers=1, progress=False,
                         scale=0.125)
    data = read_dataset(out)
    assert data.cameras["cam0"].model == "fov"
    image = data.load_image(data.map_entries[0])
    assert image.shape == (60, 80) and image.std() > 10  # a textured view, not a flat fill


def test_cli_lists_and_renders(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    add_synth_arguments(parser)
    assert main_synth(parser.parse_args(["--list"])) == 0
    assert "room-hard" in capsys.readouterr().out
    assert main_synth(parser.parse_args([])) == 2
    args = parser.parse_args(["--preset", "desk", "--out", str(tmp_path / "d"), "--seed", "2",
                              "--workers", "1", "--scale", "0.1", "--quiet"])
    assert main_synth(args) == 0
    data = read_dataset(tmp_path / "d")
    assert (len(data.map_entries), len(data.query_entries)) == (10, 10)


def test_refuses_to_write_into_a_foreign_folder(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty"):
        render_dataset(SMALL_DESK, tmp_path, seed=0, workers=1, progress=False, scale=0.1)
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_a_killed_render_worker_fails_the_run_instead_of_hanging(tmp_path) -> None:
    import multiprocessing
    import os
    import signal
    import threading
    import time

    outcome: list[BaseException | None] = []

    def render() -> None:
        try:
            render_dataset("desk", tmp_path / "desk", seed=0, scale=0.5, workers=2,
                           progress=False)
            outcome.append(None)
        except BaseException as exc:  # noqa: BLE001 - handed to the test thread
            outcome.append(exc)

    thread = threading.Thread(target=render, daemon=True)
    thread.start()
    # Mid-render, as when the kernel kills a worker for memory: once a frame is written.
    deadline = time.monotonic() + 60
    while (not any((tmp_path / "desk" / "images").rglob("*.png"))
           and time.monotonic() < deadline and thread.is_alive()):
        time.sleep(0.01)
    children = multiprocessing.active_children()
    assert children, "the render started no worker process"
    os.kill(children[0].pid, signal.SIGKILL)
    thread.join(60)
    assert not thread.is_alive(), "render_dataset hung after a worker was killed"
    assert isinstance(outcome[0], DatasetError) and "worker process died" in str(outcome[0])
