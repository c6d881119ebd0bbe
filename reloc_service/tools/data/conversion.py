"""What the dataset converters share: pose interpolation (linear translation, slerp rotation),
nearest-timestamp association, map/query frame selection and export to a reloc dataset."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ...core.cameras import Camera
from ...core.errors import DatasetError
from ...core.progress import progress
from .dataset import Dataset, DatasetEntry, read_dataset
from .dataset_write import write_dataset

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]
BoolArray = npt.NDArray[np.bool_]


def check_increasing(times: npt.NDArray[np.float64] | npt.NDArray[np.int64], what: str) -> None:
    """DatasetError naming ``what`` unless ``times`` (N,) is strictly increasing."""
    bad = np.flatnonzero(np.diff(times) <= 0)
    if bad.size:
        i = int(bad[0])
        raise DatasetError(f"{what}: timestamps must be strictly increasing; entry {i + 2} "
                           f"({times[i + 1]}) follows {times[i]}")


def bracketing_samples(query_times: Array, times: Array, *, max_dt: float
                       ) -> tuple[IntArray, IntArray, Array, BoolArray]:
    """For each query time, the samples ``lo <= t <= hi`` around it, the fraction
    ``alpha = (t - t_lo) / (t_hi - t_lo)`` and whether both lie within ``max_dt`` seconds.

    ``times`` (N,) must be strictly increasing. A query equal to a sample needs no partner."""
    n = len(times)
    if n == 0:
        zeros = np.zeros(len(query_times), dtype=np.intp)
        return zeros, zeros, np.zeros(len(query_times)), np.zeros(len(query_times), dtype=bool)
    hi = np.searchsorted(times, query_times, side="left").clip(0, n - 1)
    exact = times[hi] == query_times
    lo = np.where(exact, hi, (hi - 1).clip(0, n - 1))
    bracketed = exact | ((times[lo] < query_times) & (times[hi] > query_times))
    valid = (bracketed & (query_times - times[lo] <= max_dt) & (times[hi] - query_times <= max_dt))
    span = np.where(hi > lo, times[hi] - times[lo], 1.0)
    alpha = np.where(hi > lo, (query_times - times[lo]) / span, 0.0)
    return lo, hi, alpha, valid


def interpolate_poses(query_times: Array, times: Array, world_from_body: Array, *,
                      max_dt: float) -> tuple[Array, BoolArray]:
    """Poses (M, 4, 4) ``world_from_body`` at ``query_times`` (M,) and a (M,) validity mask.

    Between the two ground-truth samples bracketing each query time (both within ``max_dt``
    seconds) the translation is interpolated linearly and the rotation by slerp; poses of
    invalid queries are identity. ``times`` (N,) strictly increasing, poses (N, 4, 4)."""
    lo, hi, alpha, valid = bracketing_samples(query_times, times, max_dt=max_dt)
    out = np.tile(np.eye(4), (len(query_times), 1, 1))
    if not valid.any():
        return out, valid
    lo, hi, alpha = lo[valid], hi[valid], alpha[valid]
    rot_lo = Rotation.from_matrix(world_from_body[lo, :3, :3])
    rot_hi = Rotation.from_matrix(world_from_body[hi, :3, :3])
    delta = (rot_lo.inv() * rot_hi).as_rotvec()  # shortest arc, angle <= pi
    out[valid, :3, :3] = (rot_lo * Rotation.from_rotvec(alpha[:, None] * delta)).as_matrix()
    t_lo, t_hi = world_from_body[lo, :3, 3], world_from_body[hi, :3, 3]
    out[valid, :3, 3] = t_lo + alpha[:, None] * (t_hi - t_lo)
    return out, valid


def associate_nearest(query_times: Array, times: Array, *, max_dt: float) -> IntArray:
    """Index (M,) of the sample in ``times`` (N,, increasing) nearest to each query time, or -1
    where none lies within ``max_dt`` seconds."""
    if len(times) == 0:
        return np.full(len(query_times), -1, dtype=np.intp)
    hi = np.searchsorted(times, query_times).clip(0, len(times) - 1)
    lo = (hi - 1).clip(0, len(times) - 1)
    nearest = np.where(np.abs(times[lo] - query_times) <= np.abs(times[hi] - query_times), lo, hi)
    return np.where(np.abs(times[nearest] - query_times) <= max_dt, nearest, -1)


def select_frames(times: Array, *, map_stride: int, query_stride: int | None = None,
                  query_offset: int | None = None,
                  map_range: tuple[float, float] | None = None,
                  query_range: tuple[float, float] | None = None) -> tuple[IntArray, IntArray]:
    """Indices of map and query frames among frames at ``times`` (N,, seconds).

    Map frames: every ``map_stride``-th frame with a time in ``map_range`` (all frames if None).
    Query frames: every ``query_stride``-th (default ``map_stride``) frame with a time in
    ``query_range``, starting ``query_offset`` (default ``map_stride // 2``) frames into it,
    never a map frame. Ranges are inclusive ``(t0, t1)``."""
    query_stride = map_stride if query_stride is None else query_stride
    query_offset = map_stride // 2 if query_offset is None else query_offset
    if map_stride < 1 or query_stride < 1 or query_offset < 0:
        raise DatasetError(f"frame selection: expected strides >= 1 and offset >= 0, got map "
                           f"stride {map_stride}, query stride {query_stride}, query offset "
                           f"{query_offset}")
    if (map_range is None and query_range is None and query_stride == map_stride
            and query_offset % map_stride == 0):
        hint = (f"expected an offset between 1 and {map_stride - 1}" if map_stride > 1 else
                "expected a map stride of 2 or more, or map and query time ranges")
        raise DatasetError(f"frame selection: query offset {query_offset} is a multiple of the "
                           f"map stride {map_stride}, so every query would be a map frame; {hint}")
    map_idx = _in_range(times, map_range, "map")[::map_stride]
    query_idx = _in_range(times, query_range, "query")[query_offset::query_stride]
    query_idx = np.setdiff1d(query_idx, map_idx, assume_unique=True)
    if map_idx.size == 0:
        raise DatasetError(f"frame selection: no map frame in time range {map_range} (frames "
                           f"span {times[0]:.3f} .. {times[-1]:.3f} s)" if len(times) else
                           "frame selection: no frames with ground truth")
    return map_idx, query_idx


def _in_range(times: Array, time_range: tuple[float, float] | None, what: str) -> IntArray:
    if time_range is None:
        return np.arange(len(times))
    t0, t1 = time_range
    if not t0 <= t1:
        raise DatasetError(f"frame selection: {what} time range ({t0}, {t1}) is empty; "
                           "expected T0 <= T1")
    return np.flatnonzero((times >= t0) & (times <= t1))


# -- export ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class PosedFrames:
    """Frames of a source sequence that have ground truth.

    ``times`` (N,) seconds since the sequence's first image, ``image_paths`` relative to the
    source folder, ``world_from_cam`` (N, 4, 4), ``depth_paths`` (N,) relative paths or None."""

    times: Array
    image_paths: list[str]
    world_from_cam: Array
    depth_paths: list[str | None]


def export_dataset(src: Path, dst: Path, frames: PosedFrames, map_idx: IntArray,
                   query_idx: IntArray, *, camera_id: str, camera: Camera,
                   metres_per_unit: float | None = None) -> Dataset:
    """Copy the selected images (and depth maps) from ``src`` to ``dst`` keeping their relative
    paths, write the dataset files there and return the dataset as read back."""
    if dst.resolve() == src.resolve():
        raise DatasetError(f"destination {dst} is the source folder; expected a new folder")
    _check_image_size(src / frames.image_paths[int(map_idx[0])], camera)

    def entries(indices: IntArray) -> list[DatasetEntry]:
        return [DatasetEntry(frames.image_paths[i], camera_id, frames.world_from_cam[i])
                for i in indices]

    selected = np.concatenate([map_idx, query_idx])
    depth = {frames.image_paths[i]: (frames.depth_paths[i], metres_per_unit)
             for i in selected if frames.depth_paths[i] is not None and metres_per_unit}
    files = [frames.image_paths[i] for i in selected] + [png for png, _ in depth.values()]
    for rel in progress(files, desc=f"copy to {dst}"):
        _copy(src / rel, dst / rel)
    write_dataset(dst, {camera_id: camera}, entries(map_idx), entries(query_idx), depth)
    return read_dataset(dst)


def _check_image_size(path: Path, camera: Camera) -> None:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise DatasetError(f"{path}: missing or not a PNG/JPEG image")
    h, w = image.shape
    if (w, h) != camera.size:
        raise DatasetError(f"{path}: images are {w}x{h} px but the camera is "
                           f"{camera.width}x{camera.height}; pass the right camera "
                           "(--camera-json FILE)")


def _copy(source: Path, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        shutil.copyfile(source, target)
    except FileNotFoundError:
        raise DatasetError(f"missing file {source}, listed in the source sequence") from None
