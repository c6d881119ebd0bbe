"""TUM RGB-D benchmark sequence (Sturm et al., IROS 2012) to a reloc dataset v1.

A sequence folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` lines),
``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, the pose of the colour camera's optical
frame, i.e. ``world_from_cam``, at 100 Hz) and 640x480 images; depth PNGs hold 5000 units per
metre and are registered to the colour images.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera, PinholeCamera, RadTanCamera
from ...core.errors import DatasetError
from .conversion import (
    PosedFrames,
    associate_nearest,
    check_increasing,
    export_dataset,
    interpolate_poses,
    select_frames,
)
from .dataset import Dataset, image_path_problem, iter_data_lines, parse_numbers, poses_from_rows

Array = npt.NDArray[np.float64]

TUM_CAMERA_ID = "rgb"
TUM_METRES_PER_UNIT = 1.0 / 5000.0
# Calibrated colour cameras from the benchmark's "File Formats / Intrinsic Camera Calibration"
# page; freiburg3 images are already undistorted.
TUM_CAMERAS: dict[str, Camera] = {
    "freiburg1": RadTanCamera(640, 480, 517.3, 516.5, 318.6, 255.3,
                              (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": RadTanCamera(640, 480, 520.9, 521.0, 325.1, 249.7,
                              (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": PinholeCamera(640, 480, 535.4, 539.2, 320.1, 247.6),
}


def tum_default_camera(src: str | Path) -> tuple[str, Camera]:
    """(name, camera) of the TUM colour camera named in the folder name (``freiburg1/2/3`` or
    ``fr1/2/3``); freiburg1 when the name says nothing."""
    name = Path(src).resolve().name.lower()
    for key in TUM_CAMERAS:
        if key in name or f"fr{key[-1]}" in name:
            return key, TUM_CAMERAS[key]
    return "freiburg1", TUM_CAMERAS["freiburg1"]


def read_tum_file_list(path: str | Path) -> tuple[Array, list[str]]:
    """``rgb.txt`` / ``depth.txt``: timestamps (N,) seconds, sorted, and relative file names."""
    path = Path(path)
    rows = []
    for lineno, tokens in iter_data_lines(path):
        where = f"{path}:{lineno}"
        if len(tokens) != 2:
            hint = " (paths with spaces are not supported)" if len(tokens) > 2 else ""
            raise DatasetError(f"{where}: expected 2 fields 'timestamp filename', got "
                               f"{len(tokens)}{hint}")
        problem = image_path_problem(tokens[1])
        if problem:
            raise DatasetError(f"{where}: {problem}")
        rows.append((parse_numbers(tokens[:1], where, "timestamp filename")[0], tokens[1]))
    rows.sort(key=lambda row: row[0])
    times = np.array([t for t, _ in rows])
    check_increasing(times, str(path))
    return times, [name for _, name in rows]


def read_tum_trajectory(path: str | Path) -> tuple[Array, Array]:
    """``groundtruth.txt``: timestamps (N,) seconds, sorted, and ``world_from_cam`` (N, 4, 4)."""
    path = Path(path)
    layout = "timestamp tx ty tz qx qy qz qw"
    rows, wheres = [], []
    for lineno, tokens in iter_data_lines(path):
        where = f"{path}:{lineno}"
        if len(tokens) != 8:
            raise DatasetError(f"{where}: expected 8 fields '{layout}', got {len(tokens)}")
        rows.append(parse_numbers(tokens, where, layout))
        wheres.append(where)
    if not rows:
        raise DatasetError(f"{path}: no ground-truth poses")
    table = np.array(rows)
    poses = poses_from_rows(table[:, 1:], wheres, layout)
    order = np.argsort(table[:, 0], kind="stable")
    check_increasing(table[order, 0], str(path))
    return table[order, 0], poses[order]


def read_tum_frames(src: str | Path, *, max_dt: float = 0.02) -> PosedFrames:
    """The colour frames of a TUM sequence that have ground truth within ``max_dt`` seconds on
    both sides (interpolated), each with its nearest depth map within ``max_dt`` (or None)."""
    src = Path(src)
    for name in ("rgb.txt", "groundtruth.txt"):
        if not (src / name).is_file():
            raise DatasetError(f"{src}: missing {name}; expected a TUM RGB-D sequence folder "
                               "(rgb.txt, depth.txt, groundtruth.txt, rgb/, depth/)")
    rgb_times, rgb_paths = read_tum_file_list(src / "rgb.txt")
    if not rgb_paths:
        raise DatasetError(f"{src / 'rgb.txt'}: no images listed")
    gt_times, world_from_cam = read_tum_trajectory(src / "groundtruth.txt")
    poses, valid = interpolate_poses(rgb_times, gt_times, world_from_cam, max_dt=max_dt)
    if not valid.any():
        raise DatasetError(f"{src}: no colour image has ground truth within {max_dt} s on both "
                           "sides (check the timestamps or raise --max-dt)")
    depth_times, depth_paths = (read_tum_file_list(src / "depth.txt")
                                if (src / "depth.txt").is_file() else (np.zeros(0), []))
    depth_idx = associate_nearest(rgb_times, depth_times, max_dt=max_dt)
    keep = np.flatnonzero(valid)
    return PosedFrames(times=rgb_times[keep] - rgb_times[0],
                       image_paths=[rgb_paths[i] for i in keep],
                       world_from_cam=poses[keep],
                       depth_paths=[depth_paths[depth_idx[i]] if depth_idx[i] >= 0 else None
                                    for i in keep])


def convert_tum(src: str | Path, dst: str | Path, *, map_stride: int = 10,
                query_stride: int | None = None, query_offset: int | None = None,
                map_range: tuple[float, float] | None = None,
                query_range: tuple[float, float] | None = None, max_dt: float = 0.02,
                camera: Camera | None = None) -> Dataset:
    """Convert the TUM RGB-D sequence in ``src`` to a reloc dataset in ``dst`` (images and
    depth maps copied, relative paths kept) and return it.

    Frames are chosen by :func:`~reloc_service.tools.data.conversion.select_frames`; time ranges are
    seconds since the first colour image. ``camera`` defaults to the calibrated freiburg1/2/3
    colour camera named in the folder name (see :func:`tum_default_camera`)."""
    src, dst = Path(src), Path(dst)
    frames = read_tum_frames(src, max_dt=max_dt)
    map_idx, query_idx = select_frames(frames.times, map_stride=map_stride,
                                       query_stride=query_stride, query_offset=query_offset,
                                       map_range=map_range, query_range=query_range)
    camera = camera if camera is not None else tum_default_camera(src)[1]
    return export_dataset(src, dst, frames, map_idx, query_idx, camera_id=TUM_CAMERA_ID,
                          camera=camera, metres_per_unit=TUM_METRES_PER_UNIT)
