"""Writing a reloc dataset v1 (:mod:`.dataset` reads it and documents the layout): each file
validated first, then written atomically."""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
from reloc_client.protocol.geometry import rotation_to_quat_xyzw_array

from ...core.cameras import Camera
from ...core.fileio import atomic_write
from .dataset import (
    CALIBRATION_FILE,
    CALIBRATION_KEYS,
    CAMERAS_FILE,
    DEPTH_FILE,
    DEPTH_LINE,
    FORMAT,
    MAP_FILE,
    POSE_LINE,
    QUERIES_FILE,
    TRUTH_DEPTH_FILE,
    DatasetEntry,
    DatasetError,
    camera_id_problem,
    checked_calibration,
    image_path_problem,
)


def format_pose_lines(entries: list[DatasetEntry]) -> list[str]:
    """``map.txt`` lines; ``repr`` floats round-trip each pose to ~1e-16."""
    if not entries:
        return []
    poses = np.stack([e.world_from_cam for e in entries])
    quats = rotation_to_quat_xyzw_array(poses[:, :3, :3])  # w >= 0
    table = np.column_stack([poses[:, :3, 3], quats]).tolist()
    return [f"{e.image_path} {e.camera_id} " + " ".join(map(repr, row))
            for e, row in zip(entries, table, strict=True)]


def write_pose_file(path: str | Path, entries: Iterable[DatasetEntry], *, title: str = "") -> None:
    """Write ``map.txt`` / ``queries.txt`` atomically."""
    header = f"# {FORMAT}: {title + ', ' if title else ''}world_from_cam\n# {POSE_LINE}\n"
    lines = format_pose_lines(list(entries))
    atomic_write(Path(path), header + "".join(f"{line}\n" for line in lines))


def write_depth_file(path: str | Path, depth: Mapping[str, tuple[str, float]], *,
                     title: str = "depth maps") -> None:
    """Write ``depth.txt`` (or ``truth_depth.txt``) atomically."""
    lines = [f"{image} {png} {float(mpu)!r}\n" for image, (png, mpu) in depth.items()]
    atomic_write(Path(path), f"# {FORMAT}: {title}\n# {DEPTH_LINE}\n" + "".join(lines))


def write_dataset(root: str | Path, cameras: Mapping[str, Camera],
                  map_entries: Iterable[DatasetEntry], query_entries: Iterable[DatasetEntry],
                  depth: Mapping[str, tuple[str, float]] | None = None, *,
                  truth_depth: Mapping[str, tuple[str, float]] | None = None,
                  calibration_sigma: tuple[float, float] | None = None) -> None:
    """Validate, then write ``cameras.json``, ``map.txt``, ``queries.txt``, ``depth.txt``
    (sensor depth), ``truth_depth.txt`` (ground truth for scoring only) and
    ``calibration.json`` (the intrinsics' stated accuracy) under ``root``, each atomically;
    a depth file whose mapping is empty, or a calibration file when ``calibration_sigma`` is
    None, is removed (a stale one would not match). Images and depth PNGs are the caller's."""
    root = Path(root)
    map_entries, query_entries = list(map_entries), list(query_entries)
    depth, truth_depth = dict(depth or {}), dict(truth_depth or {})
    _check_for_writing(cameras, map_entries, query_entries,
                       {DEPTH_FILE: depth, TRUTH_DEPTH_FILE: truth_depth})
    if calibration_sigma is not None:
        calibration_sigma = checked_calibration(calibration_sigma, CALIBRATION_FILE)
    root.mkdir(parents=True, exist_ok=True)
    camera_lines = [f"  {json.dumps(cid)}: {json.dumps(camera.to_dict())}"
                    for cid, camera in cameras.items()]
    atomic_write(root / CAMERAS_FILE, "{\n" + ",\n".join(camera_lines) + "\n}\n")
    write_pose_file(root / MAP_FILE, map_entries, title="map keyframes")
    write_pose_file(root / QUERIES_FILE, query_entries, title="queries, ground-truth poses")
    for name, maps, title in ((DEPTH_FILE, depth, "sensor depth maps"),
                              (TRUTH_DEPTH_FILE, truth_depth,
                               "ground-truth depth maps, for scoring only")):
        if maps:
            write_depth_file(root / name, maps, title=title)
        else:
            (root / name).unlink(missing_ok=True)  # a stale depth file would not match
    if calibration_sigma is None:
        (root / CALIBRATION_FILE).unlink(missing_ok=True)
    else:
        atomic_write(root / CALIBRATION_FILE, json.dumps(
            dict(zip(CALIBRATION_KEYS, calibration_sigma, strict=True))) + "\n")


def _check_for_writing(cameras: Mapping[str, Camera], map_entries: list[DatasetEntry],
                       query_entries: list[DatasetEntry],
                       depth_files: Mapping[str, dict[str, tuple[str, float]]]) -> None:
    for camera_id, camera in cameras.items():
        problem = camera_id_problem(camera_id)
        if problem or not isinstance(camera, Camera):
            raise DatasetError(f"cameras: {problem or f'{camera_id!r} is not a Camera'}")
    for name, entries in ((MAP_FILE, map_entries), (QUERIES_FILE, query_entries)):
        seen: set[str] = set()
        for entry in entries:
            if entry.camera_id not in cameras:
                raise DatasetError(f"{name}: {entry.image_path!r} has unknown camera id "
                                   f"{entry.camera_id!r}; expected one of {sorted(cameras)}")
            if entry.image_path in seen:
                raise DatasetError(f"{name}: duplicate image path {entry.image_path!r}")
            seen.add(entry.image_path)
    known = {e.image_path for e in map_entries + query_entries}
    for name, depth in depth_files.items():
        for image_path, (depth_path, metres_per_unit) in depth.items():
            problem = image_path_problem(depth_path)
            if image_path not in known:
                problem = f"{image_path!r} is not a map or query image"
            if problem:
                raise DatasetError(f"{name}: {problem}")
            if not (math.isfinite(metres_per_unit) and metres_per_unit > 0):
                raise DatasetError(f"{name}: metres per unit of {image_path!r} is "
                                   f"{metres_per_unit}; expected a positive number")
