"""TUM RGB-D and EuRoC converters on tiny fake sequences written here, with analytic ground
truth (constant velocity, constant body rate) so interpolated poses are known exactly."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from reloc_service.core.cameras import EquidistantCamera, PinholeCamera, RadTanCamera
from reloc_service.core.errors import DatasetError
from reloc_service.core.geometry import matrix_to_quat_xyzw, so3_exp
from reloc_service.tools.data.cli import add_dataset_arguments
from reloc_service.tools.data.conversion import (
    associate_nearest,
    interpolate_poses,
    select_frames,
)
from reloc_service.tools.data.euroc import convert_euroc, parse_simple_yaml, read_euroc_sensor
from reloc_service.tools.data.tum import TUM_CAMERAS, convert_tum, tum_default_camera

SMALL = PinholeCamera(32, 24, 28.0, 28.0, 15.5, 11.5)
P0 = np.array([1.0, 2.0, 0.5])
VELOCITY = np.array([0.3, -0.2, 0.1])  # m/s
ROTATION0 = so3_exp([0.3, 0.2, -0.1])
BODY_RATE = np.array([0.2, -0.5, 0.9])  # rad/s, body frame


def analytic_pose(t: float) -> np.ndarray:
    """``world_from_x`` at ``t`` seconds: linear translation and constant body rate, so both
    linear interpolation and slerp between any two samples are exact."""
    pose = np.eye(4)
    pose[:3, :3] = ROTATION0 @ so3_exp(BODY_RATE * t)
    pose[:3, 3] = P0 + VELOCITY * t
    return pose


def tq_text(pose: np.ndarray, order: str = "xyzw") -> list[str]:
    q = matrix_to_quat_xyzw(pose[:3, :3])
    if order == "wxyz":
        q = np.roll(q, 1)
    return [repr(float(v)) for v in [*pose[:3, 3], *q]]


def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="reloc")
    add_dataset_arguments(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(list(argv))
    return args.func(args)


# -- TUM RGB-D -------------------------------------------------------------------------------

TUM_T0 = 1305031102.0
N_RGB = 24


def rgb_stamp(i: int) -> str:
    return f"{TUM_T0 + 0.0137 + i / 30:.6f}"


def make_tum(root: Path, *, size: tuple[int, int] = (32, 24)) -> Path:
    """24 colour frames at 30 Hz. Ground truth at 100 Hz on [0, 0.75] s with a gap on
    (0.405, 0.455): frames 12, 13 (gap) and 23 (after the end) have none. Depth +5 ms after
    each frame except frame 5 (-25 ms: too far). Pixels of frame i are i * 10, depth i + 1 mm."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines = ["# color images", "# file: 'fake.bag'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    w, h = size
    for i in range(N_RGB):
        stamp = rgb_stamp(i)
        colour = np.full((h, w, 3), (i * 10, i * 10, i * 10), dtype=np.uint8)
        colour[0, 0] = (255, 0, 0)  # one blue pixel: the image is colour
        cv2.imwrite(str(root / f"rgb/{stamp}.png"), colour)
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
        depth_stamp = f"{float(stamp) + (-0.025 if i == 5 else 0.005):.6f}"
        cv2.imwrite(str(root / f"depth/{depth_stamp}.png"),
                    np.full((h, w), 5 * (i + 1), dtype=np.uint16))
        depth_lines.append(f"{depth_stamp} depth/{depth_stamp}.png")
    gt_lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for k in range(76):
        if 0.405 < k / 100 < 0.455:
            continue
        stamp = f"{TUM_T0 + k / 100:.4f}"  # the pose at the parsed time: doubles near 1.3e9
        gt_lines.append(f"{stamp} " + " ".join(tq_text(analytic_pose(float(stamp) - TUM_T0))))
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines),
                        ("groundtruth.txt", gt_lines)):
        (root / name).write_text("\n".join(lines) + "\n")
    return root


def frame_index(image_path: str) -> int:
    stamp = Path(image_path).stem
    return next(i for i in range(N_RGB) if rgb_stamp(i) == stamp)


def test_tum_stride_poses_depth_and_images(tmp_path: Path) -> None:
    src = make_tum(tmp_path / "rgbd_dataset_freiburg1_fake")
    ds = convert_tum(src, tmp_path / "out", map_stride=4, camera=SMALL)

    # valid frames: 0..11, 14..22; every 4th of them is a map frame, queries 2 frames later
    assert [frame_index(e.image_path) for e in ds.map_entries] == [0, 4, 8, 14, 18, 22]
    assert [frame_index(e.image_path) for e in ds.query_entries] == [2, 6, 10, 16, 20]
    assert ds.cameras == {"rgb": SMALL}
    for entry in ds.map_entries + ds.query_entries:
        t = float(Path(entry.image_path).stem) - TUM_T0  # the same double the converter used
        np.testing.assert_allclose(entry.world_from_cam, analytic_pose(t), rtol=0, atol=1e-9)
        assert entry.image_path.startswith("rgb/")
        assert (tmp_path / "out" / entry.image_path).is_file()
        i = frame_index(entry.image_path)
        grey = ds.load_image(entry)
        assert grey.shape == (24, 32) and grey[5, 5] == i * 10
        depth = ds.load_depth(entry)
        assert depth is not None
        np.testing.assert_allclose(depth, (i + 1) * 1e-3, rtol=1e-6)
        assert ds.depth[entry.image_path][1] == pytest.approx(1 / 5000)


def test_tum_time_ranges_and_missing_depth(tmp_path: Path) -> None:
    src = make_tum(tmp_path / "seq")
    ds = convert_tum(src, tmp_path / "out", map_stride=2, query_stride=3, query_offset=0,
                     map_range=(0.0, 0.35), query_range=(0.49, 0.8), camera=SMALL)
    assert [frame_index(e.image_path) for e in ds.map_entries] == [0, 2, 4, 6, 8, 10]
    assert [frame_index(e.image_path) for e in ds.query_entries] == [15, 18, 21]
    ds = convert_tum(src, tmp_path / "out2", map_stride=1, map_range=(0.09, 0.21),
                     query_range=(0.09, 0.21), camera=SMALL)
    assert [frame_index(e.image_path) for e in ds.map_entries] == [3, 4, 5, 6]
    assert ds.query_entries == []  # queries are never map frames
    no_depth = next(e for e in ds.map_entries if frame_index(e.image_path) == 5)
    assert no_depth.image_path not in ds.depth and ds.load_depth(no_depth) is None
    assert len(ds.depth) == 3


def test_tum_default_cameras(tmp_path: Path) -> None:
    src = make_tum(tmp_path / "rgbd_dataset_freiburg1_xyz", size=(640, 480))
    ds = convert_tum(src, tmp_path / "out", map_stride=8)
    camera = ds.cameras["rgb"]
    assert isinstance(camera, RadTanCamera) and camera.size == (640, 480)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (517.3, 516.5, 318.6, 255.3)
    assert camera.distortion == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    assert tum_default_camera(tmp_path / "rgbd_dataset_freiburg3_long_office")[1] == \
        TUM_CAMERAS["freiburg3"]
    assert tum_default_camera(tmp_path / "fr2_desk")[0] == "freiburg2"
    assert tum_default_camera(tmp_path / "my_sequence")[0] == "freiburg1"
    with pytest.raises(DatasetError, match=r"images are 640x480 px but the camera is 32x24"):
        convert_tum(src, tmp_path / "out2", camera=SMALL)


def test_tum_errors(tmp_path: Path) -> None:
    src = make_tum(tmp_path / "seq")
    with pytest.raises(DatasetError, match="every query would be a map frame"):
        convert_tum(src, tmp_path / "out", map_stride=4, query_offset=8, camera=SMALL)
    with pytest.raises(DatasetError, match="no map frame in time range"):
        convert_tum(src, tmp_path / "out", map_range=(5.0, 6.0), camera=SMALL)
    with pytest.raises(DatasetError, match="is the source folder"):
        convert_tum(src, src, camera=SMALL)
    gt = src / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:5] + [lines[5].rsplit(" ", 1)[0] + " 2.0"] + lines[6:]))
    with pytest.raises(DatasetError, match=r"groundtruth\.txt:6: quaternion norm"):
        convert_tum(src, tmp_path / "out", camera=SMALL)
    gt.write_text("\n".join(lines[:3] + ["1305031102.5 1 2 3"]))
    with pytest.raises(DatasetError, match=r"groundtruth\.txt:4: expected 8 fields"):
        convert_tum(src, tmp_path / "out", camera=SMALL)
    (src / "rgb.txt").write_text("1305031102.1 rgb/a b.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:1: .*paths with spaces are not supported"):
        convert_tum(src, tmp_path / "out", camera=SMALL)
    with pytest.raises(DatasetError, match="missing rgb.txt"):
        convert_tum(tmp_path, tmp_path / "out", camera=SMALL)


def test_cli_from_tum(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = make_tum(tmp_path / "seq")
    (tmp_path / "cam.json").write_text(json.dumps(SMALL.to_dict()))
    code = run_cli("dataset", "from-tum", str(src), str(tmp_path / "out"), "--camera-json",
                   str(tmp_path / "cam.json"), "--map-stride", "3", "--query-offset", "2",
                   "--map-time", "0", "0.4", "--query-time", "0", "0.4")
    assert code == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    # frames 0..11 are in [0, 0.4] s: map 0 3 6 9, queries 2 5 8 11 (frame 5 has no depth)
    assert "map frames: 4 (4 with depth, 0 with truth depth)" in out
    assert "query frames: 4 (3 with depth" in out
    assert run_cli("dataset", "check", "--images", str(tmp_path / "out")) == 0
    assert run_cli("dataset", "from-tum", str(src), str(tmp_path / "o2"), "--map-stride", "2",
                   "--query-offset", "4") == 1
    assert "every query would be a map frame" in capsys.readouterr().err


# -- EuRoC -----------------------------------------------------------------------------------

EUROC_T0 = 1403636579763555584  # ns
EUROC_SENSOR = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [40, 30]
camera_model: pinhole
intrinsics: [35.5, 35.2, 19.7, 14.1] #fu, fv, cu, cv
distortion_model: {model}
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
BODY_FROM_CAM0 = np.array([
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0]])
BODY_FROM_CAM1 = np.eye(4)
BODY_FROM_CAM1[:3, :3] = so3_exp([0.02, -0.01, 1.58])
BODY_FROM_CAM1[:3, 3] = [-0.02, 0.045, 0.008]


def make_euroc(root: Path, n_images: int = 16) -> Path:
    """``mav0`` with cam0 (radtan) and cam1 (equidistant, another T_BS): images at 20 Hz from
    EUROC_T0 (pixels of image i are 10 i); ground truth at 200 Hz from +61.234567 ms (so images
    0 and 1 have none) to +640 ms, quaternion order w x y z, 17 columns."""
    mav = root / "mav0"
    for cam, model, body_from_cam in (("cam0", "radial-tangential", None),
                                      ("cam1", "equidistant", BODY_FROM_CAM1)):
        (mav / cam / "data").mkdir(parents=True)
        sensor = EUROC_SENSOR.replace("{model}", model)
        if body_from_cam is not None:
            rows = [", ".join(repr(float(v)) for v in row) for row in body_from_cam]
            sensor = sensor.replace(sensor[sensor.index("  data: ["):sensor.index("1.0]") + 4],
                                    "  data: [" + ",\n    ".join(rows) + "]")
        (mav / cam / "sensor.yaml").write_text(sensor)
        lines = ["#timestamp [ns],filename"]
        for i in range(n_images):
            ns = EUROC_T0 + i * 50_000_000
            cv2.imwrite(str(mav / cam / "data" / f"{ns}.png"), np.full((30, 40), 10 * i, np.uint8))
            lines.append(f"{ns},{ns}.png")
        (mav / cam / "data.csv").write_text("\n".join(lines) + "\n")
    gt = mav / "state_groundtruth_estimate0"
    gt.mkdir()
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
             "q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
             "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
             "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"]
    for k in range(116):
        offset_ns = 61_234_567 + k * 5_000_000
        fields = tq_text(analytic_pose(offset_ns * 1e-9), order="wxyz")
        lines.append(",".join([str(EUROC_T0 + offset_ns), *fields, *["0.1"] * 9]))
    (gt / "data.csv").write_text("\n".join(lines) + "\n")
    return root


def euroc_index(image_path: str) -> int:
    return (int(Path(image_path).stem) - EUROC_T0) // 50_000_000


def check_euroc_poses(ds, body_from_cam: np.ndarray) -> None:
    for entry in ds.map_entries + ds.query_entries:
        t = (int(Path(entry.image_path).stem) - EUROC_T0) * 1e-9
        np.testing.assert_allclose(entry.world_from_cam, analytic_pose(t) @ body_from_cam,
                                   rtol=0, atol=1e-9)


def test_euroc_cam0_stride(tmp_path: Path) -> None:
    src = make_euroc(tmp_path / "MH_01_easy")
    ds = convert_euroc(src, tmp_path / "out", map_stride=3, query_offset=1)
    # valid images: 2..12 (ground truth ends at +636 ms, image 12 is at +600 ms, 13 at +650)
    assert [euroc_index(e.image_path) for e in ds.map_entries] == [2, 5, 8, 11]
    assert [euroc_index(e.image_path) for e in ds.query_entries] == [3, 6, 9, 12]
    assert ds.map_entries[0].image_path == f"mav0/cam0/data/{EUROC_T0 + 100_000_000}.png"
    camera = ds.cameras["cam0"]
    assert isinstance(camera, RadTanCamera)
    assert (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy) == \
        (40, 30, 35.5, 35.2, 19.7, 14.1)
    assert camera.distortion == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    check_euroc_poses(ds, BODY_FROM_CAM0)
    assert ds.depth == {}
    assert ds.load_image(ds.query_entries[0])[0, 0] == 30


def test_euroc_cam1_time_range_from_mav0(tmp_path: Path) -> None:
    src = make_euroc(tmp_path / "V1_01")
    ds = convert_euroc(src / "mav0", tmp_path / "out", cam="cam1", map_stride=2,
                       map_range=(0.08, 0.42), query_range=(0.42, 1.0), query_offset=0)
    assert [euroc_index(e.image_path) for e in ds.map_entries] == [2, 4, 6, 8]
    assert [euroc_index(e.image_path) for e in ds.query_entries] == [9, 11]
    assert ds.map_entries[0].image_path.startswith("cam1/data/")
    assert isinstance(ds.cameras["cam1"], EquidistantCamera)
    check_euroc_poses(ds, BODY_FROM_CAM1)


def test_euroc_errors(tmp_path: Path) -> None:
    src = make_euroc(tmp_path / "seq")
    gt = src / "mav0/state_groundtruth_estimate0/data.csv"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:3] + ["1403636579900000000,1,2,3,0.5,0.5"] + lines[4:]))
    with pytest.raises(DatasetError, match=r"data\.csv:4: expected at least 8"):
        convert_euroc(src, tmp_path / "out")
    bad_q = lines[3].split(",")
    bad_q[4:8] = ["0", "0", "0", "0"]
    gt.write_text("\n".join(lines[:3] + [",".join(bad_q)] + lines[4:]))
    with pytest.raises(DatasetError, match=r"data\.csv:4: zero quaternion"):
        convert_euroc(src, tmp_path / "out")
    yaml = src / "mav0/cam0/sensor.yaml"
    yaml.write_text(yaml.read_text().replace("radial-tangential", "fov"))
    with pytest.raises(DatasetError, match="distortion_model 'fov' not supported"):
        convert_euroc(src, tmp_path / "out")
    with pytest.raises(DatasetError, match="expected a EuRoC ASL sequence"):
        convert_euroc(tmp_path / "nowhere", tmp_path / "out")


def test_simple_yaml_parser_and_sensor(tmp_path: Path) -> None:
    parsed = parse_simple_yaml(EUROC_SENSOR.replace("{model}", "equidistant"))
    assert parsed["sensor_type"] == "camera" and parsed["comment"] == "VI-Sensor cam0 (MT9M034)"
    assert parsed["T_BS"]["rows"] == 4 and len(parsed["T_BS"]["data"]) == 16
    assert parsed["resolution"] == [40, 30] and parsed["rate_hz"] == 20
    assert parsed["intrinsics"] == [35.5, 35.2, 19.7, 14.1]
    (tmp_path / "sensor.yaml").write_text(EUROC_SENSOR.replace("{model}", "radial-tangential"))
    camera, body_from_cam = read_euroc_sensor(tmp_path / "sensor.yaml")
    np.testing.assert_allclose(body_from_cam, BODY_FROM_CAM0, atol=1e-12)
    assert camera.model == "radtan"
    with pytest.raises(DatasetError, match="unterminated list"):
        parse_simple_yaml("data: [1, 2,\n 3")


# -- shared helpers --------------------------------------------------------------------------

def test_interpolation_edges_and_association() -> None:
    times = np.array([0.0, 0.01, 0.02, 0.05])
    poses = np.stack([analytic_pose(t) for t in times])
    query = np.array([-0.001, 0.0, 0.004, 0.02, 0.03, 0.05, 0.051])
    out, valid = interpolate_poses(query, times, poses, max_dt=0.02)
    assert valid.tolist() == [False, True, True, True, False, True, False]
    for q, pose, ok in zip(query, out, valid, strict=True):
        if ok:
            np.testing.assert_allclose(pose, analytic_pose(q), atol=1e-12)
    assert associate_nearest(query, times, max_dt=0.004).tolist() == [0, 0, 0, 2, -1, 3, 3]
    assert associate_nearest(query, np.zeros(0), max_dt=1.0).tolist() == [-1] * 7


def test_select_frames_queries_never_map_frames() -> None:
    times = np.arange(30) / 10
    map_idx, query_idx = select_frames(times, map_stride=3, query_stride=2, query_offset=1)
    assert map_idx.tolist() == list(range(0, 30, 3))
    assert query_idx.tolist() == [i for i in range(1, 30, 2) if i % 3]
    with pytest.raises(DatasetError, match="expected strides >= 1"):
        select_frames(times, map_stride=0)
    with pytest.raises(DatasetError, match="expected T0 <= T1"):
        select_frames(times, map_stride=2, map_range=(2.0, 1.0))
