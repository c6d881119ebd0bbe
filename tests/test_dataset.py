"""Reloc dataset v1: round trips, strict validation with file:line messages, image and depth
loading, and ``reloc dataset check``."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from reloc_service.core.cameras import (
    EquidistantCamera,
    FovCamera,
    PinholeCamera,
    RadTanCamera,
    camera_from_dict,
)
from reloc_service.core.errors import DatasetError
from reloc_service.core.geometry import se3_exp
from reloc_service.tools.data.cli import add_dataset_arguments, main_dataset
from reloc_service.tools.data.dataset import (
    Dataset,
    DatasetEntry,
    read_camera_json,
    read_dataset,
)
from reloc_service.tools.data.dataset_write import write_dataset

CAMERAS = {
    "pinhole": PinholeCamera(32, 24, 30.0, 31.0, 15.5, 11.5),
    "radtan": RadTanCamera(32, 24, 30.0, 31.0, 15.2, 11.7, (-0.28, 0.07, 2e-4, 1.8e-5, 0.01)),
    "equidistant": EquidistantCamera(32, 24, 20.0, 20.5, 16.1, 12.2, (0.01, -0.003, 4e-4, -1e-5)),
    "fov": FovCamera(32, 24, 25.0, 25.0, 15.9, 11.8, (0.93,)),
}
IDENTITY = "0 0 0 0 0 0 1"


def random_poses(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [se3_exp(np.concatenate([rng.uniform(-50, 50, 3), rng.uniform(-3, 3, 3)]))
            for _ in range(n)]


def write_files(root: Path, *, cameras: object | None = None, map_txt: str | None = None,
                queries_txt: str | None = None, depth_txt: str | None = None,
                truth_depth_txt: str | None = None) -> Path:
    """A hand-written dataset folder; ``None`` leaves a file out (cameras/map get defaults)."""
    root.mkdir(parents=True, exist_ok=True)
    if cameras is None:
        cameras = {"cam": CAMERAS["pinhole"].to_dict()}
    (root / "cameras.json").write_text(cameras if isinstance(cameras, str) else json.dumps(cameras))
    (root / "map.txt").write_text(map_txt if map_txt is not None else f"a.png cam {IDENTITY}\n")
    for name, text in (("queries.txt", queries_txt), ("depth.txt", depth_txt),
                       ("truth_depth.txt", truth_depth_txt)):
        if text is not None:
            (root / name).write_text(text)
    return root


# -- round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_round_trip_every_camera_model(tmp_path: Path, model: str) -> None:
    cameras = {"main": CAMERAS[model], "other": CAMERAS["pinhole"]}
    poses = random_poses(7, seed=len(model))
    map_entries = [DatasetEntry(f"images/m{i}.png", "main", p) for i, p in enumerate(poses[:4])]
    query_entries = [DatasetEntry(f"q/{i}.jpg", "other", p) for i, p in enumerate(poses[4:])]
    depth = {"images/m1.png": ("depth/m1.png", 0.0002), "q/0.jpg": ("depth/q0.png", 1e-3)}
    write_dataset(tmp_path, cameras, map_entries, query_entries, depth)

    ds = read_dataset(tmp_path)
    assert ds.cameras == cameras
    written_dicts = json.loads((tmp_path / "cameras.json").read_text())
    assert camera_from_dict(written_dicts["main"]) == cameras["main"]
    for written, read in zip(map_entries + query_entries, ds.map_entries + ds.query_entries,
                             strict=True):
        assert (read.image_path, read.camera_id) == (written.image_path, written.camera_id)
        assert np.abs(read.world_from_cam - written.world_from_cam).max() < 1e-9
    assert len(ds.map_entries) == 4 and len(ds.query_entries) == 3
    assert ds.depth == depth
    assert ds.camera(ds.query_entries[0]) == cameras["other"]
    assert not list(tmp_path.glob(".*.tmp")), "temporary files left behind"


def test_round_trip_extreme_values_to_1e9(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    poses = []
    for scale in (1e-7, 1.0, 1e4):
        pose = se3_exp(rng.normal(size=6))
        pose[:3, 3] = rng.normal(size=3) * scale
        poses.append(pose)
    entries = [DatasetEntry(f"{i}.png", "c", p) for i, p in enumerate(poses)]
    write_dataset(tmp_path, {"c": CAMERAS["radtan"]}, entries, [])
    read = read_dataset(tmp_path).map_entries
    for a, b in zip(entries, read, strict=True):
        assert np.abs(a.world_from_cam - b.world_from_cam).max() < 1e-9


def test_comments_blank_lines_and_absent_queries(tmp_path: Path) -> None:
    half = np.sqrt(0.5)
    write_files(tmp_path, map_txt=f"""# header comment

  a.png cam 1 2 3 0 0 {half} {half}   # trailing comment
b.png cam 4 5 6 {IDENTITY[6:]} #another

   # indented comment
c.png  cam\t7 8 9 0 0 0 1
""")
    ds = read_dataset(tmp_path)
    assert [e.image_path for e in ds.map_entries] == ["a.png", "b.png", "c.png"]
    assert ds.query_entries == [] and ds.depth == {}
    np.testing.assert_allclose(ds.map_entries[0].world_from_cam[:3, :3],
                               [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(ds.map_entries[2].world_from_cam[:3, 3], [7, 8, 9])


def test_nearly_unit_quaternion_is_normalised(tmp_path: Path) -> None:
    write_files(tmp_path, map_txt="a.png cam 0 0 0 0 0 0.3 0.9543\n")  # norm 1.00031
    rotation = read_dataset(tmp_path).map_entries[0].world_from_cam[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)


def test_entries_are_immutable_and_normalised() -> None:
    pose = np.eye(4)
    entry = DatasetEntry("./img/../img/a.png", "cam", pose)
    pose[0, 3] = 5.0
    assert entry.image_path == "img/a.png" and entry.world_from_cam[0, 3] == 0.0
    with pytest.raises(ValueError):
        entry.world_from_cam[0, 3] = 1.0
    with pytest.raises(DatasetError, match="spaces are not supported"):
        DatasetEntry("my image.png", "cam", np.eye(4))
    with pytest.raises(DatasetError, match="world_from_cam"):
        DatasetEntry("a.png", "cam", np.diag([2.0, 1.0, 1.0, 1.0]))


# -- malformed input -------------------------------------------------------------------------

MAP_ERRORS = [
    ("wrong field count", f"a.png cam {IDENTITY}\nb.png cam 0 0 0 0 0 1\n", "map.txt:2",
     "expected 9 fields"),
    ("path with spaces", f"a.png cam {IDENTITY}\nmy image.png cam {IDENTITY}\n", "map.txt:2",
     "spaces are not supported"),
    ("non-numeric", "a.png cam 0 0 zero 0 0 0 1\n", "map.txt:1", "'zero' is not a number"),
    ("nan", "a.png cam 0 nan 0 0 0 0 1\n", "map.txt:1", "not finite"),
    ("inf quaternion", "a.png cam 0 0 0 0 0 0 inf\n", "map.txt:1", "not finite"),
    ("zero quaternion", "# c\na.png cam 0 0 0 0 0 0 0\n", "map.txt:2", "zero quaternion"),
    ("non-unit quaternion", "a.png cam 0 0 0 0 0 0 1.01\n", "map.txt:1", "norm is 1.010000"),
    ("unknown camera", f"a.png cam {IDENTITY}\nb.png cam9 {IDENTITY}\n", "map.txt:2",
     "unknown camera id 'cam9'"),
    ("duplicate image", f"a.png cam {IDENTITY}\n\nb.png cam {IDENTITY}\n./a.png cam {IDENTITY}\n",
     "map.txt:4", "duplicate image path 'a.png' (first listed on line 1)"),
    ("absolute path", f"/data/a.png cam {IDENTITY}\n", "map.txt:1", "absolute"),
    ("backslash", f"img\\a.png cam {IDENTITY}\n", "map.txt:1", "forward slashes"),
]


@pytest.mark.parametrize(("case", "text", "where", "expected"), MAP_ERRORS,
                         ids=[c[0] for c in MAP_ERRORS])
def test_malformed_map_lines(tmp_path: Path, case: str, text: str, where: str,
                             expected: str) -> None:
    write_files(tmp_path, map_txt=text)
    with pytest.raises(DatasetError) as info:
        read_dataset(tmp_path)
    assert where in str(info.value) and expected in str(info.value), str(info.value)


def test_malformed_queries_name_queries_file(tmp_path: Path) -> None:
    write_files(tmp_path, queries_txt=f"q.png cam {IDENTITY}\nr.png cam 0 0 0 0 0 0\n")
    with pytest.raises(DatasetError, match=r"queries\.txt:2: expected 9 fields"):
        read_dataset(tmp_path)


DEPTH_ERRORS = [
    ("image not listed", "z.png d/z.png 0.001\n", "depth.txt:1", "not listed in map.txt"),
    ("negative scale", "a.png d/a.png -0.001\n", "depth.txt:1", "expected a positive number"),
    ("zero scale", "# c\n\na.png d/a.png 0\n", "depth.txt:3", "expected a positive number"),
    ("field count", "a.png d/a.png\n", "depth.txt:1", "expected 3 fields"),
    ("non-numeric scale", "a.png d/a.png mm\n", "depth.txt:1", "'mm' is not a number"),
    ("second depth", "a.png d/a.png 0.001\nq.png d/q.png 1\na.png d/b.png 0.001\n",
     "depth.txt:3", "second depth map"),
]


@pytest.mark.parametrize(("case", "text", "where", "expected"), DEPTH_ERRORS,
                         ids=[c[0] for c in DEPTH_ERRORS])
def test_malformed_depth_lines(tmp_path: Path, case: str, text: str, where: str,
                               expected: str) -> None:
    write_files(tmp_path, queries_txt=f"q.png cam {IDENTITY}\n", depth_txt=text)
    with pytest.raises(DatasetError) as info:
        read_dataset(tmp_path)
    assert where in str(info.value) and expected in str(info.value), str(info.value)


@pytest.mark.parametrize(("case", "text", "where", "expected"), DEPTH_ERRORS,
                         ids=[c[0] for c in DEPTH_ERRORS])
def test_malformed_truth_depth_lines_name_truth_depth_file(tmp_path: Path, case: str, text: str,
                                                           where: str, expected: str) -> None:
    write_files(tmp_path, queries_txt=f"q.png cam {IDENTITY}\n", depth_txt="a.png d/a.png 1e-3\n",
                truth_depth_txt=text)
    with pytest.raises(DatasetError) as info:
        read_dataset(tmp_path)
    assert f"truth_{where}" in str(info.value) and expected in str(info.value), str(info.value)


def test_truth_depth_file_is_optional(tmp_path: Path) -> None:
    """Datasets written before truth_depth.txt existed read as before."""
    write_files(tmp_path, queries_txt=f"q.png cam {IDENTITY}\n", depth_txt="q.png dq.png 1e-3\n")
    ds = read_dataset(tmp_path)
    assert ds.truth_depth == {} and ds.depth == {"q.png": ("dq.png", 1e-3)}
    assert Dataset(ds.root, ds.cameras, ds.map_entries).truth_depth == {}  # positional as before


def test_depth_may_name_query_images(tmp_path: Path) -> None:
    write_files(tmp_path, queries_txt=f"q.png cam {IDENTITY}\n", depth_txt="q.png dq.png 1e-3\n")
    assert read_dataset(tmp_path).depth == {"q.png": ("dq.png", 1e-3)}


CAMERA_ERRORS = [
    ("bad focal", {"cam": {**CAMERAS["pinhole"].to_dict(), "fx": -1.0}}, "camera 'cam'",
     "positive"),
    ("unknown model", {"cam": {**CAMERAS["pinhole"].to_dict(), "model": "kb8"}}, "camera 'cam'",
     "unknown model"),
    ("wrong distortion count", {"cam": {**CAMERAS["fov"].to_dict(), "distortion": [0.1, 0.2]}},
     "camera 'cam'", "distortion values"),
    ("not an object", [1, 2], "cameras.json", "expected a non-empty JSON object"),
    ("empty", {}, "cameras.json", "(empty)"),
    ("id with space", {"my cam": CAMERAS["pinhole"].to_dict()}, "cameras.json", "whitespace"),
    ("invalid json", '{\n  "cam": {\n    "model": "pinhole",,\n', "cameras.json:3",
     "invalid JSON"),
]


@pytest.mark.parametrize(("case", "cameras", "where", "expected"), CAMERA_ERRORS,
                         ids=[c[0] for c in CAMERA_ERRORS])
def test_malformed_cameras(tmp_path: Path, case: str, cameras: object, where: str,
                           expected: str) -> None:
    write_files(tmp_path, cameras=cameras)
    with pytest.raises(DatasetError) as info:
        read_dataset(tmp_path)
    message = str(info.value)
    assert "cameras.json" in message and where in message and expected in message, message


def test_missing_files(tmp_path: Path) -> None:
    write_files(tmp_path)
    (tmp_path / "cameras.json").unlink()
    with pytest.raises(DatasetError, match=r"missing .*cameras\.json: expected a JSON object"):
        read_dataset(tmp_path)
    write_files(tmp_path)
    (tmp_path / "map.txt").unlink()
    with pytest.raises(DatasetError, match=r"missing .*map\.txt"):
        read_dataset(tmp_path)
    with pytest.raises(DatasetError, match="does not exist"):
        read_dataset(tmp_path / "nowhere")


def test_write_rejects_inconsistent_input(tmp_path: Path) -> None:
    cams = {"cam": CAMERAS["pinhole"]}
    entry = DatasetEntry("a.png", "cam", np.eye(4))
    with pytest.raises(DatasetError, match="unknown camera id 'other'"):
        write_dataset(tmp_path, cams, [DatasetEntry("b.png", "other", np.eye(4))], [])
    with pytest.raises(DatasetError, match="duplicate image path 'a.png'"):
        write_dataset(tmp_path, cams, [entry, entry], [])
    with pytest.raises(DatasetError, match="not a map or query image"):
        write_dataset(tmp_path, cams, [entry], [], {"x.png": ("d.png", 0.001)})
    with pytest.raises(DatasetError, match="positive"):
        write_dataset(tmp_path, cams, [entry], [], {"a.png": ("d.png", -1.0)})
    assert not (tmp_path / "map.txt").exists(), "nothing is written when validation fails"


def test_write_rejects_bad_truth_depth_naming_its_file(tmp_path: Path) -> None:
    cams = {"cam": CAMERAS["pinhole"]}
    entry = DatasetEntry("a.png", "cam", np.eye(4))
    with pytest.raises(DatasetError, match=r"truth_depth\.txt: 'x\.png' is not a map or query"):
        write_dataset(tmp_path, cams, [entry], [], truth_depth={"x.png": ("d.png", 0.001)})
    with pytest.raises(DatasetError, match=r"truth_depth\.txt: .* expected a positive number"):
        write_dataset(tmp_path, cams, [entry], [], truth_depth={"a.png": ("d.png", math.nan)})
    with pytest.raises(DatasetError, match=r"truth_depth\.txt: .*absolute"):
        write_dataset(tmp_path, cams, [entry], [], truth_depth={"a.png": ("/d.png", 0.001)})
    assert not (tmp_path / "map.txt").exists()


def test_rewrite_without_depth_removes_stale_depth_file(tmp_path: Path) -> None:
    cams = {"cam": CAMERAS["pinhole"]}
    entry = DatasetEntry("a.png", "cam", np.eye(4))
    write_dataset(tmp_path, cams, [entry], [], {"a.png": ("d.png", 0.001)})
    assert read_dataset(tmp_path).depth
    write_dataset(tmp_path, cams, [DatasetEntry("b.png", "cam", np.eye(4))], [])
    ds = read_dataset(tmp_path)
    assert ds.depth == {} and [e.image_path for e in ds.map_entries] == ["b.png"]
    write_dataset(tmp_path, cams, [entry], [], truth_depth={"a.png": ("t.png", 0.001)})
    assert (tmp_path / "truth_depth.txt").is_file() and not (tmp_path / "depth.txt").exists()
    write_dataset(tmp_path, cams, [entry], [])
    assert not (tmp_path / "truth_depth.txt").exists()


def test_read_camera_json_accepts_dict_or_single_camera_file(tmp_path: Path) -> None:
    cam = CAMERAS["equidistant"]
    (tmp_path / "a.json").write_text(json.dumps(cam.to_dict()))
    (tmp_path / "b.json").write_text(json.dumps({"left": cam.to_dict()}))
    (tmp_path / "c.json").write_text(json.dumps({"l": cam.to_dict(), "r": cam.to_dict()}))
    assert read_camera_json(tmp_path / "a.json") == cam == read_camera_json(tmp_path / "b.json")
    with pytest.raises(DatasetError, match="c.json"):
        read_camera_json(tmp_path / "c.json")


# -- images and depth ------------------------------------------------------------------------

def image_dataset(tmp_path: Path) -> tuple[Dataset, np.ndarray]:
    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, size=(24, 32, 3), dtype=np.uint8)
    colour = cv2.GaussianBlur(colour, (5, 5), 1.5)  # smooth, so JPEG stays close
    (tmp_path / "img").mkdir()
    cv2.imwrite(str(tmp_path / "img/colour.png"), colour)
    cv2.imwrite(str(tmp_path / "img/colour.jpg"), colour, [cv2.IMWRITE_JPEG_QUALITY, 98])
    cv2.imwrite(str(tmp_path / "img/grey.png"), colour[:, :, 1])
    cv2.imwrite(str(tmp_path / "img/small.png"), colour[:20])
    (tmp_path / "img/broken.png").write_bytes(b"not an image at all")
    names = ["colour.png", "colour.jpg", "grey.png", "small.png", "broken.png", "missing.png"]
    entries = [DatasetEntry(f"img/{n}", "cam", np.eye(4)) for n in names]
    write_dataset(tmp_path, {"cam": CAMERAS["radtan"]}, entries, [])
    return read_dataset(tmp_path), colour


def test_load_image_png_jpeg_colour_and_grey(tmp_path: Path) -> None:
    ds, colour = image_dataset(tmp_path)
    by_name = {e.image_path.split("/")[-1]: e for e in ds.map_entries}
    expected_grey = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    png = ds.load_image(by_name["colour.png"])
    assert png.dtype == np.uint8 and png.shape == (24, 32)
    assert np.abs(png.astype(int) - expected_grey).max() <= 1
    jpg = ds.load_image(by_name["colour.jpg"])
    assert jpg.dtype == np.uint8 and jpg.shape == (24, 32)
    assert np.abs(jpg.astype(float) - expected_grey).mean() < 3.0
    np.testing.assert_array_equal(ds.load_image(by_name["grey.png"]), colour[:, :, 1])


@pytest.mark.parametrize(("name", "expected"), [
    ("small.png", "image is 32x20 px, but camera 'cam' expects 32x24"),
    ("broken.png", "cannot decode; expected a PNG or JPEG"),
    ("missing.png", "missing image file"),
])
def test_load_image_errors(tmp_path: Path, name: str, expected: str) -> None:
    ds, _ = image_dataset(tmp_path)
    entry = next(e for e in ds.map_entries if e.image_path.endswith(name))
    with pytest.raises(DatasetError, match=expected) as info:
        ds.load_image(entry)
    assert name in str(info.value)


def test_load_depth(tmp_path: Path) -> None:
    raw = np.arange(24 * 32, dtype=np.uint16).reshape(24, 32) * 7
    raw[3, 4] = 0
    (tmp_path / "d").mkdir()
    cv2.imwrite(str(tmp_path / "d/a.png"), raw)
    cv2.imwrite(str(tmp_path / "d/eight_bit.png"), (raw % 256).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "d/small.png"), raw[:10])
    entries = [DatasetEntry(n, "cam", np.eye(4)) for n in ("a.png", "b.png", "c.png", "e.png")]
    depth = {"a.png": ("d/a.png", 0.0002), "b.png": ("d/eight_bit.png", 0.001),
             "c.png": ("d/small.png", 0.001)}
    write_dataset(tmp_path, {"cam": CAMERAS["pinhole"]}, entries, [], depth)
    ds = read_dataset(tmp_path)

    metres = ds.load_depth(ds.map_entries[0])
    assert metres is not None and metres.dtype == np.float32 and metres.shape == (24, 32)
    assert np.isnan(metres[3, 4]) and np.isnan(metres).sum() == 2  # raw[0, 0] is 0 too
    valid = raw > 0
    np.testing.assert_allclose(metres[valid], raw[valid] * 0.0002, rtol=1e-6)
    with pytest.raises(DatasetError, match="16-bit"):
        ds.load_depth(ds.map_entries[1])
    with pytest.raises(DatasetError, match="expects 32x24"):
        ds.load_depth(ds.map_entries[2])
    assert ds.load_depth(ds.map_entries[3]) is None


def test_truth_depth_round_trip_and_fallback_to_sensor_depth(tmp_path: Path) -> None:
    """truth_depth.txt round-trips; load_truth_depth prefers it, falls back to depth.txt (a
    real RGB-D dataset's only depth), else None; load_depth never reads the truth."""
    truth_raw = np.full((24, 32), 1500, np.uint16)
    sensor_raw = np.full((24, 32), 1503, np.uint16)
    sensor_raw[5, 6] = 0  # a sensor hole
    (tmp_path / "d").mkdir()
    cv2.imwrite(str(tmp_path / "d/truth_a.png"), truth_raw)
    cv2.imwrite(str(tmp_path / "d/sensor.png"), sensor_raw)
    names = ("a.png", "b.png", "c.png")
    entries = [DatasetEntry(n, "cam", np.eye(4)) for n in names]
    sensor = {"a.png": ("d/sensor.png", 0.001), "b.png": ("d/sensor.png", 0.001)}
    truth = {"a.png": ("d/truth_a.png", 0.001), "q.png": ("d/truth_a.png", 0.001)}
    write_dataset(tmp_path, {"cam": CAMERAS["pinhole"]}, entries,
                  [DatasetEntry("q.png", "cam", np.eye(4))], sensor, truth_depth=truth)
    assert (tmp_path / "truth_depth.txt").read_text().startswith(
        "# reloc dataset v1: ground-truth depth maps, for scoring only\n")
    assert not list(tmp_path.glob(".*.tmp")), "temporary files left behind"

    ds = read_dataset(tmp_path)
    assert ds.truth_depth == truth and ds.depth == sensor
    a, b, c = ds.map_entries
    truth_a, sensor_a = ds.load_truth_depth(a), ds.load_depth(a)
    assert truth_a is not None and sensor_a is not None
    np.testing.assert_allclose(truth_a, 1.5, rtol=1e-6)
    assert np.isnan(sensor_a[5, 6]) and np.nanmax(sensor_a) == pytest.approx(1.503)
    fallback = ds.load_truth_depth(b)
    assert fallback is not None and np.isnan(fallback[5, 6])  # sensor depth: the best there is
    assert ds.load_truth_depth(c) is None and ds.load_depth(c) is None
    query_truth = ds.load_truth_depth(ds.query_entries[0])
    assert query_truth is not None and ds.load_depth(ds.query_entries[0]) is None


# -- reloc dataset check ---------------------------------------------------------------------

def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="reloc")
    add_dataset_arguments(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(list(argv))
    return args.func(args)


def test_cli_check_prints_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    poses = random_poses(5)
    write_dataset(tmp_path, {"cam": CAMERAS["fov"]},
                  [DatasetEntry(f"{i}.png", "cam", p) for i, p in enumerate(poses[:3])],
                  [DatasetEntry("q.png", "cam", poses[3]), DatasetEntry("0.png", "cam", poses[4])])
    assert run_cli("dataset", "check", str(tmp_path)) == 0
    out = capsys.readouterr().out
    assert "fov 32x24" in out and "map frames: 3" in out
    assert "query frames: 2 (0 with depth, 0 with truth depth, 1 also in the map)" in out
    x_min = min(p[0, 3] for p in poses)
    assert f"x [{x_min:.3f}," in out


def test_cli_check_reports_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_files(tmp_path, map_txt=f"a.png cam {IDENTITY}\na.png cam {IDENTITY}\n")
    assert run_cli("dataset", "check", str(tmp_path)) == 1
    assert "map.txt:2: duplicate image path" in capsys.readouterr().err
    write_files(tmp_path)
    assert run_cli("dataset", "check", "--images", str(tmp_path)) == 1  # a.png does not exist
    assert "missing image file" in capsys.readouterr().err


def test_main_dataset_also_fills_a_plain_parser() -> None:
    parser = argparse.ArgumentParser(prog="reloc dataset")
    add_dataset_arguments(parser)
    args = parser.parse_args(["check", "somewhere"])
    assert args.func is main_dataset and args.dataset == "somewhere"


# -- calibration.json ------------------------------------------------------------------------

def test_calibration_sigma_round_trip_and_stale_file_removed(tmp_path: Path) -> None:
    cams = {"cam": CAMERAS["pinhole"]}
    entry = DatasetEntry("a.png", "cam", np.eye(4))
    write_dataset(tmp_path, cams, [entry], [])
    assert read_dataset(tmp_path).calibration_sigma is None
    write_dataset(tmp_path, cams, [entry], [], calibration_sigma=(0.002, 0.5))
    assert read_dataset(tmp_path).calibration_sigma == (0.002, 0.5)
    write_dataset(tmp_path, cams, [entry], [])
    assert not (tmp_path / "calibration.json").exists()
    for bad in ((-0.1, 1.0), (0.0, float("nan"))):
        with pytest.raises(DatasetError, match="focal_sigma_rel"):
            write_dataset(tmp_path, cams, [entry], [], calibration_sigma=bad)


@pytest.mark.parametrize("text", [
    "not json",
    "[0.1, 0.2]",
    '{"focal_sigma_rel": 0.1}',
    '{"focal_sigma_rel": 0.1, "radial_sigma_px": -1}',
    '{"focal_sigma_rel": true, "radial_sigma_px": 1}',
    '{"focal_sigma_rel": 0.1, "radial_sigma_px": 1, "k1": 0}',
])
def test_malformed_calibration_file_names_it(tmp_path: Path, text: str) -> None:
    root = write_files(tmp_path)
    (root / "calibration.json").write_text(text)
    with pytest.raises(DatasetError, match=r"calibration\.json.*focal_sigma_rel"):
        read_dataset(root)
