"""``reloc dataset from-rosbag`` / ``to-rosbag`` on real recordings written by rosbags: the real
TUM fr1_rpy frames shipped with the tests (and the full development set where it is present)
go into MCAP and SQLite3 bags and come back as the same map; bags with a missing topic, a
wrong type, no odometry or another clock are refused with a clear error."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from reloc_service.core.geometry import invert, pose_from_tum, rotation_angle
from reloc_service.service.ros2 import types as ros
from reloc_service.service.ros2.conf import Ros2Conf
from reloc_service.tools.data import rosbag_cli
from reloc_service.tools.data.cli import add_dataset_arguments
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.data.rosbag_images import stamp_name
from reloc_service.tools.data.rosbag_write import (
    BagLayout,
    camera_info_message,
    header_message,
    odometry_message,
    stem_stamp_ns,
)

REPO = Path(__file__).resolve().parents[1]
MINI = REPO / "tests" / "data" / "tum_fr1_rpy_mini"
# The real development sets live next to the repository (absent from a clean CI clone).
REAL = Path(os.environ.get("RELOC_REAL_DATA", REPO / ".." / "shared" / "data" / "real")).resolve()
IMAGE, INFO, ODOM = "/camera/image_raw/compressed", "/camera/camera_info", "/odom"
#: The mini set's map lies in its first 2.2 s, its queries 16 s later (a second pass).
MINI_SPLIT = ("--map-time", "0", "10", "--query-time", "10", "1000")


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("RELOC_PROGRESS", "0")


def run_cli(*argv: str | Path) -> int:
    parser = argparse.ArgumentParser(prog="reloc")
    add_dataset_arguments(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args([str(a) for a in argv])
    return args.func(args)


def to_bag(tmp_path: Path, *options: str, src: Path = MINI, name: str = "bag") -> Path:
    bag = tmp_path / name
    assert run_cli("dataset", "to-rosbag", src, bag, *options) == 0
    return bag


def from_bag(bag: Path, dst: Path, *options: str) -> int:
    return run_cli("dataset", "from-rosbag", bag, dst, "--image-topic", IMAGE, *options)


def assert_same_dataset(converted: Path, original: Path, *, atol: float = 1e-12) -> None:
    """Same cameras, same map and query images (paths, camera ids, bytes), poses to ``atol``."""
    a, b = read_dataset(converted), read_dataset(original)
    assert json.loads((converted / "cameras.json").read_text()) == \
        json.loads((original / "cameras.json").read_text())
    for got, want in ((a.map_entries, b.map_entries), (a.query_entries, b.query_entries)):
        assert [(e.image_path, e.camera_id) for e in got] == \
            [(e.image_path, e.camera_id) for e in want]
        for e, f in zip(got, want, strict=True):
            np.testing.assert_allclose(e.world_from_cam, f.world_from_cam, rtol=0, atol=atol)
            assert (converted / e.image_path).read_bytes() == (original / f.image_path).read_bytes()


# -- the round trip --------------------------------------------------------------------------

@pytest.mark.parametrize("storage, suffix", [("mcap", ".mcap"), ("sqlite3", ".db3")])
def test_a_bag_of_the_real_frames_converts_back_to_the_same_map(tmp_path, storage, suffix):
    bag = to_bag(tmp_path, "--storage", storage)
    assert [p.suffix for p in bag.iterdir() if p.name != "metadata.yaml"] == [suffix]
    assert from_bag(bag, tmp_path / "out", "--odometry-topic", ODOM,
                    "--camera-info-topic", INFO, *MINI_SPLIT) == 0
    assert_same_dataset(tmp_path / "out", MINI)


def test_the_storage_file_alone_is_read_too(tmp_path):
    bag = to_bag(tmp_path)
    (mcap,) = bag.glob("*.mcap")
    assert from_bag(mcap, tmp_path / "out", "--odometry-topic", ODOM,
                    "--camera-info-topic", INFO, *MINI_SPLIT) == 0
    assert_same_dataset(tmp_path / "out", MINI)


def test_poses_from_tf_give_the_same_map(tmp_path):
    bag = to_bag(tmp_path, "--tf-topic", "/tf", "--storage", "sqlite3")
    assert from_bag(bag, tmp_path / "out", "--tf-parent", "odom", "--tf-child", "/base_link",
                    "--camera-info-topic", INFO, *MINI_SPLIT) == 0
    assert_same_dataset(tmp_path / "out", MINI)


def test_the_camera_mounting_is_applied_as_the_bridge_applies_it(tmp_path):
    mount = ["0.1", "-0.02", "0.05", "0.5", "-0.5", "0.5", "-0.5"]   # a forward-looking camera
    bag = to_bag(tmp_path, "--body-from-cam", *mount)
    assert from_bag(bag, tmp_path / "same", "--odometry-topic", ODOM, "--camera-info-topic",
                    INFO, "--body-from-cam", *mount, *MINI_SPLIT) == 0
    assert_same_dataset(tmp_path / "same", MINI)
    # Without the mounting the body's pose is taken for the camera's.
    assert from_bag(bag, tmp_path / "body", "--odometry-topic", ODOM, "--camera-info-topic",
                    INFO, *MINI_SPLIT) == 0
    body_from_cam = pose_from_tum([float(v) for v in mount])
    for got, want in zip(read_dataset(tmp_path / "body").map_entries,
                         read_dataset(MINI).map_entries, strict=True):
        np.testing.assert_allclose(got.world_from_cam, want.world_from_cam @ invert(body_from_cam),
                                   atol=1e-12)


def test_intrinsics_on_the_command_line_make_a_pinhole_camera_of_the_image_size(tmp_path):
    bag = to_bag(tmp_path)
    assert from_bag(bag, tmp_path / "out", "--odometry-topic", ODOM, "--intrinsics", "517.3",
                    "516.5", "318.6", "255.3", "--camera-id", "cam0") == 0
    dataset = read_dataset(tmp_path / "out")
    assert dataset.cameras["cam0"].to_dict() == {
        "model": "pinhole", "width": 640, "height": 480, "fx": 517.3, "fy": 516.5, "cx": 318.6,
        "cy": 255.3, "distortion": []}
    assert len(dataset.map_entries) == 12 and not dataset.query_entries   # default: all frames


# -- choosing keyframes and queries ----------------------------------------------------------

def test_queries_are_held_out_first_then_every_nth_remaining_frame_is_a_keyframe(tmp_path):
    bag = to_bag(tmp_path)
    assert from_bag(bag, tmp_path / "out", "--odometry-topic", ODOM, "--camera-info-topic",
                    INFO, "--queries-every", "3", "--keyframe-every", "2") == 0
    frames = sorted(e.image_path for e in read_dataset(MINI).map_entries
                    + read_dataset(MINI).query_entries)
    out = read_dataset(tmp_path / "out")
    assert [e.image_path for e in out.query_entries] == [frames[i] for i in (1, 4, 7, 10)]
    assert [e.image_path for e in out.map_entries] == [frames[i] for i in (0, 3, 6, 9)]
    truth = {e.image_path: e.world_from_cam for e in read_dataset(MINI).map_entries
             + read_dataset(MINI).query_entries}
    for entry in out.query_entries:   # a query's ground truth is its odometry pose
        np.testing.assert_allclose(entry.world_from_cam, truth[entry.image_path], atol=1e-12)


def test_the_bridges_keyframe_rule_keeps_frames_apart(tmp_path):
    bag = to_bag(tmp_path)
    assert from_bag(bag, tmp_path / "out", "--odometry-topic", ODOM, "--camera-info-topic",
                    INFO, "--keyframe-rule", "0.05", "10", *MINI_SPLIT) == 0
    kept = [e.world_from_cam for e in read_dataset(tmp_path / "out").map_entries]
    assert 1 < len(kept) < 9
    for i, pose in enumerate(kept):   # each keyframe is far from or turned from all before it
        for earlier in kept[:i]:
            distance = np.linalg.norm(pose[:3, 3] - earlier[:3, 3])
            angle = np.degrees(rotation_angle(earlier[:3, :3].T @ pose[:3, :3]))
            assert distance > 0.05 or angle > 10


def test_images_without_odometry_within_the_tolerance_are_left_out(tmp_path, capsys):
    stamps = [1_000_000_000 + i * 100_000_000 for i in range(6)]
    write_bag(tmp_path / "bag", images=stamps, odometry=[s + 30_000_000 for s in stamps[:3]]
              + [s + 5_000_000 for s in stamps[3:]])
    assert from_bag(tmp_path / "bag", tmp_path / "out", "--odometry-topic", ODOM,
                    "--camera-info-topic", INFO) == 0
    out = read_dataset(tmp_path / "out")
    assert [e.image_path for e in out.map_entries] == [
        f"images/{stamp_name(s)}.png" for s in stamps[3:]]
    assert "3 paired with a pose, 3 without a pose" in capsys.readouterr().out


def test_a_topic_whose_type_hash_rosbags_computes_differently_does_not_stop_the_bag(tmp_path):
    # rosbags' own hash of a type with a ``char`` field differs from rosidl's (the official
    # one a real recording carries); its high-level reader refuses such a bag at open.
    assert ros.type_hash("std_msgs/msg/Char") != ros.typestore().hash_rihs01("std_msgs/msg/Char")
    stamps = [1_000_000_000, 1_100_000_000]
    write_bag(tmp_path / "bag", images=stamps, odometry=stamps, char_topic=True)
    assert from_bag(tmp_path / "bag", tmp_path / "out", "--odometry-topic", ODOM,
                    "--camera-info-topic", INFO) == 0
    assert len(read_dataset(tmp_path / "out").map_entries) == 2


def test_pose_stamped_odometry_is_read_as_the_bridge_reads_it(tmp_path):
    stamps = [1_000_000_000, 1_100_000_000, 1_200_000_000]
    write_bag(tmp_path / "bag", images=stamps, odometry=[s + 4_000_000 for s in stamps],
              odometry_type=ros.POSE_STAMPED)
    assert from_bag(tmp_path / "bag", tmp_path / "out", "--odometry-topic", ODOM,
                    "--camera-info-topic", INFO) == 0
    xs = [e.world_from_cam[0, 3] for e in read_dataset(tmp_path / "out").map_entries]
    np.testing.assert_allclose(xs, [1.004, 1.104, 1.204], atol=1e-12)


# -- raw images and damaged ones -------------------------------------------------------------

def test_raw_images_become_grey_pngs_of_the_same_pixels(tmp_path):
    colour = cv2.imread(str(MINI / read_dataset(MINI).map_entries[0].image_path))
    stamps = [2_000_000_000, 2_100_000_000]
    write_bag(tmp_path / "bag", images=stamps, odometry=stamps, raw=colour, image_topic="/raw")
    assert run_cli("dataset", "from-rosbag", tmp_path / "bag", tmp_path / "out", "--image-topic",
                   "/raw", "--odometry-topic", ODOM, "--camera-info-topic", INFO) == 0
    out = read_dataset(tmp_path / "out")
    grey = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    for entry in out.map_entries:
        assert entry.image_path.endswith(".png")
        np.testing.assert_array_equal(out.load_image(entry), grey)


def test_an_image_that_does_not_decode_is_skipped_and_reported(tmp_path, capsys):
    stamps = [1_000_000_000 + i * 100_000_000 for i in range(4)]
    write_bag(tmp_path / "bag", images=stamps, odometry=stamps, corrupt={stamps[1]})
    assert from_bag(tmp_path / "bag", tmp_path / "out", "--odometry-topic", ODOM,
                    "--camera-info-topic", INFO) == 0
    assert len(read_dataset(tmp_path / "out").map_entries) == 3
    assert "skipped 1 image(s): PNG bytes that do not decode" in capsys.readouterr().out


# -- refusals: exit status 1, one line naming what was expected, nothing written ---------------

def refused(capsys, bag: Path, dst: Path, *options: str) -> str:
    assert from_bag(bag, dst, *options) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "Traceback" not in err
    assert not dst.exists()
    return err


def test_a_missing_topic_is_named_with_the_topics_present(tmp_path, capsys):
    bag = to_bag(tmp_path)
    err = refused(capsys, bag, tmp_path / "out", "--odometry-topic", "/vio/odom",
                  "--camera-info-topic", INFO)
    assert "no topic /vio/odom (odometry, expected nav_msgs/msg/Odometry" in err
    assert f"{ODOM} (nav_msgs/msg/Odometry, 12 messages)" in err


def test_a_topic_of_the_wrong_type_is_named_with_its_type(tmp_path, capsys):
    bag = to_bag(tmp_path)
    err = refused(capsys, bag, tmp_path / "out", "--odometry-topic", INFO,
                  "--camera-info-topic", INFO)
    assert f"topic {INFO} (odometry) holds sensor_msgs/msg/CameraInfo; expected" in err
    err = refused(capsys, bag, tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", IMAGE)
    assert f"topic {IMAGE} (camera info) holds sensor_msgs/msg/CompressedImage" in err


def test_a_bag_with_no_odometry_is_refused(tmp_path, capsys):
    write_bag(tmp_path / "none", images=[1_000_000_000], odometry=None)
    err = refused(capsys, tmp_path / "none", tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", INFO)
    assert f"no topic {ODOM} (odometry" in err and "all topics: " + INFO in err
    write_bag(tmp_path / "empty", images=[1_000_000_000], odometry=[])
    err = refused(capsys, tmp_path / "empty", tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", INFO)
    assert f"topic {ODOM} (odometry, nav_msgs/msg/Odometry) has no messages" in err


def test_odometry_on_another_clock_is_refused_with_both_spans(tmp_path, capsys):
    stamps = [1_000_000_000 + i * 100_000_000 for i in range(4)]
    write_bag(tmp_path / "bag", images=stamps, odometry=[s + 1_000_000_000 for s in stamps])
    err = refused(capsys, tmp_path / "bag", tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", INFO)
    assert "images from 1.000 to 1.300 s, 4 poses from 2.000 to 2.300 s" in err
    assert "within 0.02 s" in err and "--max-stamp-difference" in err


def test_a_missing_transform_lists_the_transforms_present(tmp_path, capsys):
    bag = to_bag(tmp_path, "--tf-topic", "/tf")
    err = refused(capsys, bag, tmp_path / "out", "--tf-parent", "map", "--tf-child", "base_link",
                  "--camera-info-topic", INFO)
    assert "no pose in transform map -> base_link on /tf" in err
    assert "transforms on /tf: odom -> base_link (12)" in err


def test_a_camera_of_another_size_is_refused_and_nothing_is_left(tmp_path, capsys):
    bag = to_bag(tmp_path)
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"model": "pinhole", "width": 320, "height": 240, "fx": 260,
                                  "fy": 260, "cx": 160, "cy": 120}))
    err = refused(capsys, bag, tmp_path / "out", "--odometry-topic", ODOM, "--camera-json",
                  str(camera))
    assert "is 640x480 px but the camera is 320x240" in err


def test_a_camera_info_reloc_cannot_use_or_that_changes_is_refused(tmp_path, capsys):
    stamps = [1_000_000_000, 1_100_000_000]
    write_bag(tmp_path / "changes", images=stamps, odometry=stamps,
              infos=(("plumb_bob", 517.306408), ("plumb_bob", 600.0)))
    err = refused(capsys, tmp_path / "changes", tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", INFO)
    assert f"topic {INFO}: the camera changes 1 time(s) during the recording" in err
    write_bag(tmp_path / "later", images=stamps, odometry=stamps,
              infos=(("plumb_bob", 517.306408), ("kannala", 500.0)))
    err = refused(capsys, tmp_path / "later", tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", INFO)
    assert "the camera changes 1 time(s)" in err
    write_bag(tmp_path / "model", images=stamps, odometry=stamps, infos=(("kannala", 500.0),))
    err = refused(capsys, tmp_path / "model", tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", INFO)
    assert f"topic {INFO}: camera_info: distortion model 'kannala'" in err


def test_bad_arguments_and_places_are_refused(tmp_path, capsys):
    bag = to_bag(tmp_path)
    err = refused(capsys, bag, tmp_path / "out", "--odometry-topic", ODOM)
    assert "camera: expected exactly one of a CameraInfo topic" in err
    err = refused(capsys, bag, tmp_path / "out", "--odometry-topic", ODOM, "--tf-parent", "odom",
                  "--tf-child", "base_link", "--camera-info-topic", INFO)
    assert "not both or neither" in err
    err = refused(capsys, MINI, tmp_path / "out", "--odometry-topic", ODOM,
                  "--camera-info-topic", INFO)
    assert "no metadata.yaml in this folder" in err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    assert from_bag(bag, tmp_path / "full", "--odometry-topic", ODOM,
                    "--camera-info-topic", INFO) == 1
    assert "exists and is not an empty folder" in capsys.readouterr().err
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"
    assert run_cli("dataset", "to-rosbag", MINI, bag) == 1
    assert "exists; expected a new path" in capsys.readouterr().err


def test_the_command_exits_1_without_a_traceback(tmp_path):
    bag = to_bag(tmp_path)
    done = subprocess.run([sys.executable, "-m", "reloc_service.cli.main", "dataset",
                           "from-rosbag", str(bag), str(tmp_path / "out"), "--image-topic",
                           "/nope", "--odometry-topic", ODOM, "--camera-info-topic", INFO],
                          capture_output=True, text=True, timeout=60, cwd=REPO)
    assert done.returncode == 1, done.stderr
    assert "no topic /nope (images" in done.stderr and "Traceback" not in done.stderr


# -- small parts -----------------------------------------------------------------------------

def test_image_names_and_stamps():
    assert stamp_name(1305031232_961662000) == "1305031232.961662"
    assert stamp_name(12_500_000_000) == "12.500000"
    assert stamp_name(3_000_000_001) == "3.000000001"
    assert stem_stamp_ns("1305031232.961662") == 1305031232_961662000
    assert stem_stamp_ns("1403636579763555584") == 1403636579763555584   # EuRoC, ns
    assert stem_stamp_ns("frame_0001") is None and stem_stamp_ns("0001") is None


def test_the_command_line_defaults_are_the_bridges():
    conf = Ros2Conf()
    assert (rosbag_cli.BRIDGE_IMAGE_TOPIC, rosbag_cli.BRIDGE_CAMERA_INFO_TOPIC,
            rosbag_cli.BRIDGE_ODOMETRY_TOPIC, rosbag_cli.BRIDGE_MAX_STAMP_DIFFERENCE_S) == (
        conf.image_topic, conf.camera_info_topic, conf.odometry_topic,
        conf.max_stamp_difference_s)


# -- the real development set and the eval table (slow) ---------------------------------------

def eval_rows(dataset: Path) -> dict[str, float]:
    """What ``reloc eval`` scores on ``dataset`` with its default method, latency left out."""
    from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
    from reloc_service.tools.eval.evaluate import evaluate

    summary = evaluate(dataset, [DEFAULT_METHOD], progress=False).method(DEFAULT_METHOD).summary
    return {**{f"recall {k}": v for k, v in summary.recall.items()},
            "wrong": summary.wrong_rate, "off": summary.off_rate,
            "relocalized": summary.relocalized, "not relocalized": summary.not_relocalized_rate,
            "median t": summary.median_t_err_m, "median r": summary.median_r_err_deg}


def same_table(got: dict[str, float], want: dict[str, float]) -> bool:
    """Equal rows; errors to 1e-6 (poses equal to 1e-12 may move their last digits)."""
    return got == pytest.approx(want, rel=1e-6, nan_ok=True)


@pytest.mark.slow
def test_the_mini_set_through_a_bag_scores_the_same_eval_table(tmp_path):
    bag = to_bag(tmp_path)
    assert from_bag(bag, tmp_path / "out", "--odometry-topic", ODOM, "--camera-info-topic",
                    INFO, *MINI_SPLIT) == 0
    table = eval_rows(MINI)
    assert table["relocalized"] == 3
    assert same_table(eval_rows(tmp_path / "out"), table)


@pytest.mark.slow
@pytest.mark.skipif(not (REAL / "tum_fr1_rpy").is_dir(), reason=f"no real sets at {REAL}")
def test_the_real_tum_fr1_rpy_set_through_a_bag_gives_the_same_map_and_eval_table(tmp_path):
    real = REAL / "tum_fr1_rpy"
    bag = to_bag(tmp_path, "--storage", "mcap", src=real)
    # Map frames span the first 12 s of the sequence, queries (a later pass) start at 13.5 s.
    assert from_bag(bag, tmp_path / "out", "--odometry-topic", ODOM, "--camera-info-topic",
                    INFO, "--map-time", "0", "12.5", "--query-time", "12.5", "1000") == 0
    assert_same_dataset(tmp_path / "out", real)
    table = eval_rows(real)
    assert table["relocalized"] >= 8
    assert same_table(eval_rows(tmp_path / "out"), table)


# -- bags written here, message by message ----------------------------------------------------

def write_bag(path: Path, *, images: list[int], odometry: list[int] | None,
              raw: np.ndarray | None = None, image_topic: str = IMAGE,
              corrupt: set[int] = frozenset(), char_topic: bool = False,
              odometry_type: str = ros.ODOMETRY,
              infos: tuple[tuple[str, float], ...] = ()) -> None:  # type: ignore[assignment]
    """A bag of the mini set's first image at ``images`` stamps (ns; a CompressedImage PNG, or
    ``raw`` as a bgr8 Image), its CameraInfo once, and odometry (:func:`shift`) at ``odometry``
    stamps (None: no odometry topic), of ``odometry_type`` (Odometry or PoseStamped);
    ``char_topic``: also a std_msgs/Char topic under its official type hash, as ROS 2 records
    it; ``infos``: (distortion model, fx) of each CameraInfo (default: one, the set's)."""
    from rosbags.rosbag2 import Writer

    from reloc_service.tools.data.dataset import read_cameras

    first = read_dataset(MINI).map_entries[0]
    png = (MINI / first.image_path).read_bytes()
    camera = read_cameras(MINI / "cameras.json")[first.camera_id]
    store, layout = ros.typestore(), BagLayout()
    with Writer(path, version=9) as writer:
        image_type = ros.IMAGE if raw is not None else ros.COMPRESSED_IMAGE
        image_conn = writer.add_connection(image_topic, image_type, typestore=store)
        info_conn = writer.add_connection(INFO, ros.CAMERA_INFO, typestore=store)
        odom_conn = (writer.add_connection(ODOM, odometry_type, typestore=store)
                     if odometry is not None else None)
        if char_topic:
            msgdef, _ = store.generate_msgdef("std_msgs/msg/Char", ros_version=2)
            char_conn = writer.add_connection("/status_char", "std_msgs/msg/Char", msgdef=msgdef,
                                              rihs01=ros.type_hash("std_msgs/msg/Char"))
            writer.write(char_conn, images[0], ros.encode(ros.message("std_msgs/msg/Char",
                                                                      data=65), "std_msgs/msg/Char"))
        for i, (model, fx) in enumerate(infos or (("plumb_bob", camera.fx),)):
            info = camera_info_message(camera, header_message(images[0] + i, "cam"))
            info.distortion_model, info.k[0] = model, fx
            writer.write(info_conn, images[0] + i, ros.encode(info, ros.CAMERA_INFO))
        for stamp in images:
            header = header_message(stamp, "cam")
            if raw is not None:
                msg = ros.message(ros.IMAGE, header=header, height=raw.shape[0],
                                  width=raw.shape[1], encoding="bgr8", is_bigendian=0,
                                  step=raw.shape[1] * 3, data=raw.ravel())
            else:
                data = png[:200] if stamp in corrupt else png
                msg = ros.message(ros.COMPRESSED_IMAGE, header=header, format="png",
                                  data=np.frombuffer(data, np.uint8))
            writer.write(image_conn, stamp, ros.encode(msg, image_type))
        for stamp in odometry or []:
            assert odom_conn is not None
            odometry_msg = odometry_message(np.eye(4) + shift(stamp), stamp, layout)
            if odometry_type == ros.POSE_STAMPED:
                odometry_msg = ros.message(ros.POSE_STAMPED, header=odometry_msg.header,
                                           pose=odometry_msg.pose.pose)
            writer.write(odom_conn, stamp, ros.encode(odometry_msg, odometry_type))


def shift(stamp_ns: int) -> np.ndarray:
    """The odometry of the bags written here: the body moves 1 m/s along x."""
    out = np.zeros((4, 4))
    out[0, 3] = stamp_ns * 1e-9
    return out
