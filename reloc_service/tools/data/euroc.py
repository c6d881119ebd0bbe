"""EuRoC MAV sequence in ASL format (Burri et al., IJRR 2016) to a reloc dataset v1.

Layout read (``SRC`` is the sequence folder holding ``mav0/``, or ``mav0`` itself)::

    mav0/cam0/data.csv                          #timestamp [ns],filename
    mav0/cam0/data/<timestamp>.png
    mav0/cam0/sensor.yaml                       T_BS (body_from_cam), intrinsics, distortion
    mav0/state_groundtruth_estimate0/data.csv   timestamp, p_RS_R xyz, q_RS_R w x y z, ...

The ground truth is the body (IMU) pose ``world_from_body``; the camera pose is
``world_from_cam = world_from_body @ body_from_cam`` with ``body_from_cam = T_BS``.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ...core.cameras import CAMERA_MODELS, Camera
from ...core.errors import CameraError, DatasetError
from .conversion import (
    PosedFrames,
    check_increasing,
    export_dataset,
    interpolate_poses,
    select_frames,
)
from .dataset import Dataset, image_path_problem, parse_numbers, poses_from_rows

Array = npt.NDArray[np.float64]

GROUNDTRUTH = "state_groundtruth_estimate0"
DISTORTION_MODELS = {"radial-tangential": "radtan", "radtan": "radtan",
                     "equidistant": "equidistant", "equi": "equidistant"}
_GT_LAYOUT = "timestamp [ns], p_RS_R x y z [m], q_RS w x y z, ..."


# -- sensor.yaml -----------------------------------------------------------------------------

def parse_simple_yaml(text: str, where: str = "yaml") -> dict[str, Any]:
    """The flat YAML of EuRoC ``sensor.yaml``: ``key: value`` lines, one level of indented
    mappings, flow lists ``[a, b, ...]`` that may span lines, ``#`` comments. Numbers become
    int/float, other scalars strings. Not a general YAML parser."""
    result: dict[str, Any] = {}
    parent: dict[str, Any] | None = None
    pending: tuple[dict[str, Any], str, str, int] | None = None  # open flow list
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].rstrip()
        if pending is not None:
            target, key, value, start = pending
            pending = _store(target, key, value + " " + line.strip(), start, where)
            continue
        if not line.strip() or line.strip() in ("---", "%YAML:1.0"):
            continue
        key, sep, value = line.strip().partition(":")
        if not sep or not key:
            raise DatasetError(f"{where}:{lineno}: expected 'key: value', got {raw.strip()!r}")
        nested = line[0].isspace()
        if nested and parent is None:
            raise DatasetError(f"{where}:{lineno}: indented line outside a mapping")
        target = parent if nested and parent is not None else result
        if not nested and not value.strip():
            parent = result[key.strip()] = {}
            continue
        parent = parent if nested else None
        pending = _store(target, key.strip(), value.strip(), lineno, where)
    if pending is not None:
        raise DatasetError(f"{where}:{pending[3]}: unterminated list for {pending[1]!r}")
    return result


def _store(target: dict[str, Any], key: str, value: str, lineno: int, where: str
           ) -> tuple[dict[str, Any], str, str, int] | None:
    """Store ``key: value``; return the still-open list state if ``value`` is an unclosed list."""
    if value.startswith("[") and value.count("[") > value.count("]"):
        return target, key, value, lineno
    if value.startswith("["):
        inner = value.strip()[1:-1]
        target[key] = [_scalar(v.strip()) for v in inner.split(",") if v.strip()]
    else:
        target[key] = _scalar(value)
    return None


def _scalar(text: str) -> Any:
    try:
        return ast.literal_eval(text) if text[:1] not in "'\"" else text[1:-1]
    except (ValueError, SyntaxError):
        return text


def read_euroc_sensor(path: str | Path) -> tuple[Camera, Array]:
    """(camera, ``body_from_cam`` (4, 4)) from a EuRoC camera ``sensor.yaml``."""
    path = Path(path)
    try:
        yaml = parse_simple_yaml(path.read_text(encoding="utf-8"), str(path))
    except FileNotFoundError:
        raise DatasetError(f"missing {path}: expected the camera's sensor.yaml") from None
    return _camera_from_yaml(yaml, path), _body_from_cam(yaml, path)


def _camera_from_yaml(yaml: dict[str, Any], path: Path) -> Camera:
    def numbers(key: str, count: int) -> list[float]:
        values = yaml.get(key)
        if (not isinstance(values, list) or len(values) != count
                or not all(isinstance(v, int | float) for v in values)):
            raise DatasetError(f"{path}: expected '{key}' to be a list of {count} numbers, "
                               f"got {values!r}")
        return [float(v) for v in values]

    if yaml.get("camera_model", "pinhole") != "pinhole":
        raise DatasetError(f"{path}: camera_model {yaml['camera_model']!r} not supported; "
                           "expected 'pinhole'")
    distortion_model = yaml.get("distortion_model")
    if distortion_model not in DISTORTION_MODELS:
        raise DatasetError(f"{path}: distortion_model {distortion_model!r} not supported; "
                           f"expected one of {sorted(DISTORTION_MODELS)}")
    width, height = numbers("resolution", 2)
    fx, fy, cx, cy = numbers("intrinsics", 4)
    try:
        return CAMERA_MODELS[DISTORTION_MODELS[distortion_model]](
            int(width), int(height), fx, fy, cx, cy,
            tuple(numbers("distortion_coefficients", 4)))
    except CameraError as exc:
        raise DatasetError(f"{path}: {exc}") from exc


def _body_from_cam(yaml: dict[str, Any], path: Path) -> Array:
    block = yaml.get("T_BS")
    data = block.get("data") if isinstance(block, dict) else None
    if (not isinstance(data, list) or len(data) != 16
            or not all(isinstance(v, int | float) for v in data)):
        raise DatasetError(f"{path}: expected T_BS with 'data' holding 16 numbers (4x4, row "
                           f"major), got {block!r}")
    body_from_cam = np.array(data, dtype=np.float64).reshape(4, 4)
    rotation = body_from_cam[:3, :3]
    err = np.abs(rotation @ rotation.T - np.eye(3)).max()
    if err > 1e-3 or np.linalg.det(rotation) < 0 or not np.allclose(body_from_cam[3], [0, 0, 0, 1]):
        raise DatasetError(f"{path}: T_BS is not a rigid transform (|R R^T - I| = {err:.1e}, "
                           f"last row {body_from_cam[3].tolist()})")
    # Printed calibrations are orthonormal to ~1e-9 only: snap to the nearest rotation.
    body_from_cam[:3, :3] = Rotation.from_matrix(rotation).as_matrix()
    return body_from_cam


# -- csv files -------------------------------------------------------------------------------

def _csv_rows(path: Path, min_fields: int, layout: str) -> list[tuple[str, list[str]]]:
    """(``file:line``, fields) of each non-comment row with at least ``min_fields`` fields."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(f"missing {path}: expected a CSV file '{layout}'") from None
    rows = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        if not raw.strip() or raw.lstrip().startswith("#"):
            continue
        fields = [f.strip() for f in raw.split(",")]
        if len(fields) < min_fields:
            raise DatasetError(f"{path}:{lineno}: expected at least {min_fields} comma-separated "
                               f"fields '{layout}', got {len(fields)}")
        rows.append((f"{path}:{lineno}", fields))
    return rows


def _nanoseconds(token: str, where: str) -> int:
    try:
        return int(token)
    except ValueError:
        raise DatasetError(f"{where}: timestamp {token!r} is not an integer number of "
                           "nanoseconds") from None


def read_euroc_images(path: str | Path) -> tuple[npt.NDArray[np.int64], list[str]]:
    """A camera's ``data.csv``: timestamps (N,) int64 ns, sorted, and file names."""
    path = Path(path)
    rows = []
    for where, fields in _csv_rows(path, 2, "#timestamp [ns],filename"):
        problem = image_path_problem(fields[1])
        if problem:
            raise DatasetError(f"{where}: {problem}")
        rows.append((_nanoseconds(fields[0], where), fields[1]))
    if not rows:
        raise DatasetError(f"{path}: no images listed")
    rows.sort()
    stamps = np.array([ns for ns, _ in rows], dtype=np.int64)
    check_increasing(stamps, str(path))
    return stamps, [name for _, name in rows]


def read_euroc_groundtruth(path: str | Path) -> tuple[npt.NDArray[np.int64], Array]:
    """``state_groundtruth_estimate0/data.csv``: timestamps (N,) int64 ns, sorted, and
    ``world_from_body`` (N, 4, 4) (the file's quaternion order is w x y z)."""
    path = Path(path)
    stamps, rows, wheres = [], [], []
    for where, fields in _csv_rows(path, 8, _GT_LAYOUT):
        stamps.append(_nanoseconds(fields[0], where))
        rows.append(parse_numbers(fields[1:8], where, _GT_LAYOUT))
        wheres.append(where)
    if not rows:
        raise DatasetError(f"{path}: no ground-truth poses")
    p_qwxyz = np.array(rows)
    poses = poses_from_rows(p_qwxyz[:, [0, 1, 2, 4, 5, 6, 3]], wheres, _GT_LAYOUT)  # w last
    stamp_array = np.array(stamps, dtype=np.int64)
    order = np.argsort(stamp_array, kind="stable")
    check_increasing(stamp_array[order], str(path))
    return stamp_array[order], poses[order]


# -- conversion ------------------------------------------------------------------------------

def euroc_base(src: str | Path) -> Path:
    """The ``mav0`` folder of a EuRoC sequence given the sequence folder or ``mav0`` itself."""
    src = Path(src)
    for base in (src / "mav0", src):
        if (base / GROUNDTRUTH).is_dir() or (base / "cam0").is_dir():
            return base
    raise DatasetError(f"{src}: expected a EuRoC ASL sequence folder (mav0/cam0/data.csv, "
                       f"mav0/{GROUNDTRUTH}/data.csv)")


def read_euroc_frames(src: str | Path, *, cam: str = "cam0", max_dt: float = 0.02
                      ) -> tuple[PosedFrames, Camera]:
    """The images of camera ``cam`` that have ground truth within ``max_dt`` seconds on both
    sides, with ``world_from_cam`` interpolated at the image timestamps, and the camera."""
    src = Path(src)
    base = euroc_base(src)
    camera, body_from_cam = read_euroc_sensor(base / cam / "sensor.yaml")
    stamps, names = read_euroc_images(base / cam / "data.csv")
    gt_stamps, world_from_body = read_euroc_groundtruth(base / GROUNDTRUTH / "data.csv")
    # Seconds relative to the first image: int64 differences keep nanosecond precision.
    times = (stamps - stamps[0]) * 1e-9
    poses, valid = interpolate_poses(times, (gt_stamps - stamps[0]) * 1e-9, world_from_body,
                                     max_dt=max_dt)
    if not valid.any():
        raise DatasetError(f"{src}: no {cam} image has ground truth within {max_dt} s on both "
                           "sides (check the timestamps or raise --max-dt)")
    keep = np.flatnonzero(valid)
    prefix = (base / cam / "data").relative_to(src).as_posix()
    return PosedFrames(times=times[keep],
                       image_paths=[f"{prefix}/{names[i]}" for i in keep],
                       world_from_cam=poses[keep] @ body_from_cam,
                       depth_paths=[None] * len(keep)), camera


def convert_euroc(src: str | Path, dst: str | Path, *, cam: str = "cam0", map_stride: int = 10,
                  query_stride: int | None = None, query_offset: int | None = None,
                  map_range: tuple[float, float] | None = None,
                  query_range: tuple[float, float] | None = None, max_dt: float = 0.02,
                  camera: Camera | None = None) -> Dataset:
    """Convert camera ``cam`` of the EuRoC sequence in ``src`` to a reloc dataset in ``dst``
    (images copied, relative paths kept) and return it.

    Frames are chosen by :func:`~reloc_service.tools.data.conversion.select_frames`; time ranges are
    seconds since the camera's first image. ``camera`` overrides the one in ``sensor.yaml``."""
    src, dst = Path(src), Path(dst)
    frames, sensor_camera = read_euroc_frames(src, cam=cam, max_dt=max_dt)
    map_idx, query_idx = select_frames(frames.times, map_stride=map_stride,
                                       query_stride=query_stride, query_offset=query_offset,
                                       map_range=map_range, query_range=query_range)
    return export_dataset(src, dst, frames, map_idx, query_idx, camera_id=cam,
                          camera=camera if camera is not None else sensor_camera)
