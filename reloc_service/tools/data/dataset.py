"""Reloc dataset v1: ``cameras.json``, ``map.txt``, ``queries.txt``, ``depth.txt``,
``truth_depth.txt``; strict reading that names file and line (:mod:`.dataset_write` writes it).

Layout of a dataset folder ``DATASET``::

    cameras.json  {"<camera id>": Camera.to_dict(), ...}
    map.txt       <image path> <camera id> tx ty tz qx qy qz qw     one line per map keyframe
    queries.txt   same layout, the pose is ground truth used only for scoring (optional)
    depth.txt     <image path> <16-bit depth png> <metres per unit>  (optional)
    truth_depth.txt  same layout (optional)
    calibration.json  {"focal_sigma_rel": F, "radial_sigma_px": R}  (optional)

``depth.txt`` is sensor depth the user has (an RGB-D camera): the map builder may use it.
``truth_depth.txt`` is ground-truth depth used only for scoring (landmark accuracy), never to
build the map (a synthetic monocular or stereo dataset has it, but no ``depth.txt``).

``calibration.json`` is how accurate whoever made the dataset says ``cameras.json``'s
intrinsics are, 1 sigma: the focal length relative to itself, and the radial distortion as
pixels at the farthest image corner; ``reloc synth`` writes 0, 0 (rendered through the exact
camera). Absent: not stated, and readers assume the map configuration's default.

Poses are ``world_from_cam`` (camera x right, y down, z forward), quaternions Hamilton x y z w.
``#`` at the start of a line or of a whitespace-separated token starts a comment; blank lines
are ignored. Paths are relative to ``DATASET`` with forward slashes and may not contain
whitespace (the format is whitespace-separated).
"""

from __future__ import annotations

import json
import math
import posixpath
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from reloc_client.protocol.geometry import quat_xyzw_to_rotation

from ...core.cameras import Camera, camera_from_dict
from ...core.errors import CameraError, DatasetError, GeometryError
from ...core.geometry import check_pose

Array = npt.NDArray[np.float64]

FORMAT = "reloc dataset v1"
CAMERAS_FILE = "cameras.json"
MAP_FILE = "map.txt"
QUERIES_FILE = "queries.txt"
DEPTH_FILE = "depth.txt"
TRUTH_DEPTH_FILE = "truth_depth.txt"
CALIBRATION_FILE = "calibration.json"
CALIBRATION_KEYS = ("focal_sigma_rel", "radial_sigma_px")

POSE_LINE = "<image path> <camera id> tx ty tz qx qy qz qw"
DEPTH_LINE = "<image path> <depth png path> <metres per unit>"
QUAT_NORM_TOL = 1e-3  # quaternions printed with few digits are renormalised, not rejected


@dataclass(frozen=True, eq=False)
class DatasetEntry:
    """One image of a dataset with its camera and ``world_from_cam`` (4, 4) float64 pose.

    ``eq=False``: the pose is an array, compare fields explicitly. The pose is copied and made
    read-only, so an entry is immutable."""

    image_path: str
    camera_id: str
    world_from_cam: Array

    def __post_init__(self) -> None:
        problem = image_path_problem(self.image_path) or camera_id_problem(self.camera_id)
        if problem:
            raise DatasetError(f"dataset entry {self.image_path!r}: {problem}")
        try:
            pose = check_pose(self.world_from_cam, name=f"world_from_cam of {self.image_path!r}")
        except GeometryError as exc:
            raise DatasetError(str(exc)) from exc
        pose = pose.copy()
        pose.setflags(write=False)
        object.__setattr__(self, "image_path", posixpath.normpath(self.image_path))
        object.__setattr__(self, "world_from_cam", pose)


@dataclass
class Dataset:
    """A reloc dataset v1 in memory; images and depth maps are loaded on demand from ``root``."""

    root: Path
    cameras: dict[str, Camera]
    map_entries: list[DatasetEntry]
    query_entries: list[DatasetEntry] = field(default_factory=list)
    depth: dict[str, tuple[str, float]] = field(default_factory=dict)
    truth_depth: dict[str, tuple[str, float]] = field(default_factory=dict)
    #: (relative focal, radial pixels at the farthest corner), 1 sigma, from
    #: ``calibration.json``; None when the dataset does not state it.
    calibration_sigma: tuple[float, float] | None = None

    def camera(self, entry: DatasetEntry) -> Camera:
        """The camera that took ``entry``'s image."""
        try:
            return self.cameras[entry.camera_id]
        except KeyError:
            raise DatasetError(f"{self.root}: unknown camera id {entry.camera_id!r} for "
                               f"{entry.image_path!r}; known: {sorted(self.cameras)}") from None

    def load_image(self, entry: DatasetEntry) -> npt.NDArray[np.uint8]:
        """(H, W) uint8 grey image of ``entry`` (PNG or JPEG, colour converted to grey, EXIF
        orientation ignored); DatasetError if missing, undecodable or not the camera's size."""
        import cv2

        path = self.root / entry.image_path
        image = _decode_image(path, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
        _check_size(path, image, self.camera(entry), entry.camera_id)
        return image

    def load_depth(self, entry: DatasetEntry) -> npt.NDArray[np.float32] | None:
        """(H, W) float32 depth in metres along the optical axis, NaN where the sensor had no
        value (raw 0); None if ``depth.txt`` lists no depth map for ``entry``."""
        item = self.depth.get(entry.image_path)
        return None if item is None else self._read_depth_png(entry, *item)

    def load_truth_depth(self, entry: DatasetEntry) -> npt.NDArray[np.float32] | None:
        """Ground-truth depth of ``entry`` for scoring, as :meth:`load_depth`: the map of
        ``truth_depth.txt`` if it lists one, else the sensor depth of ``depth.txt`` (real RGB-D
        datasets have only that), else None."""
        item = self.truth_depth.get(entry.image_path)
        return self.load_depth(entry) if item is None else self._read_depth_png(entry, *item)

    def _read_depth_png(self, entry: DatasetEntry, depth_path: str,
                        metres_per_unit: float) -> npt.NDArray[np.float32]:
        """Decode one 16-bit depth PNG of ``entry`` to metres (NaN where raw is 0)."""
        import cv2

        path = self.root / depth_path
        raw = _decode_image(path, cv2.IMREAD_UNCHANGED)
        if raw.ndim != 2 or raw.dtype != np.uint16:
            raise DatasetError(f"{path}: expected a single-channel 16-bit depth PNG, got "
                               f"{raw.dtype} with shape {raw.shape}")
        _check_size(path, raw, self.camera(entry), entry.camera_id)
        metres = (raw * metres_per_unit).astype(np.float32)
        metres[raw == 0] = np.nan
        return metres


# -- validation of single fields ------------------------------------------------------------

def image_path_problem(path: str) -> str | None:
    """Why ``path`` cannot be an image path of a dataset, or None if it can."""
    if not isinstance(path, str) or not path:
        return "expected a non-empty relative path"
    if any(c.isspace() for c in path):
        return f"path {path!r} contains whitespace; paths with spaces are not supported"
    if "\\" in path:
        return f"path {path!r} contains a backslash; expected forward slashes"
    if path.startswith("/") or (len(path) > 1 and path[1] == ":"):
        return f"path {path!r} is absolute; expected a path relative to the dataset folder"
    if path.startswith("#"):
        return f"path {path!r} starts with '#', which starts a comment"
    return None


def camera_id_problem(camera_id: str) -> str | None:
    """Why ``camera_id`` cannot be a camera id, or None if it can."""
    if not isinstance(camera_id, str) or not camera_id:
        return "camera id must be a non-empty string"
    if any(c.isspace() for c in camera_id) or camera_id.startswith("#"):
        return f"camera id {camera_id!r} may not contain whitespace or start with '#'"
    return None


# -- reading ---------------------------------------------------------------------------------

def iter_data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """Yield (1-based line number, whitespace-separated tokens) of every non-blank line of
    ``path``, with ``#`` comments (at line start or token start) removed."""
    for lineno, raw in enumerate(_read_text(path).splitlines(), 1):
        tokens = raw.split()
        for i, token in enumerate(tokens):
            if token.startswith("#"):
                del tokens[i:]
                break
        if tokens:
            yield lineno, tokens


def parse_numbers(tokens: list[str], where: str, layout: str) -> Array:
    """Tokens to a float64 array; DatasetError at ``where`` (``file:line``) naming ``layout``
    if one is not a finite number."""
    try:
        values = np.array([float(token) for token in tokens])
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise DatasetError(f"{where}: {bad!r} is not a number; expected {layout}") from None
    if not np.isfinite(values).all():
        bad = tokens[int(np.flatnonzero(~np.isfinite(values))[0])]
        raise DatasetError(f"{where}: {bad!r} is not finite; expected {layout} as finite numbers")
    return values


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def poses_from_rows(values: Array, wheres: list[str], layout: str = "tx ty tz qx qy qz qw"
                    ) -> Array:
    """Rows ``tx ty tz qx qy qz qw`` (N, 7), finite, to (N, 4, 4) poses; each quaternion must
    have unit norm within 1e-3 and is then normalised. DatasetError at the first bad row's
    ``wheres[i]`` (``file:line``) otherwise. Vectorised: ground-truth files have 1e4+ rows."""
    values = np.asarray(values, dtype=np.float64).reshape(-1, 7)
    norms = np.linalg.norm(values[:, 3:7], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        where, norm = wheres[bad[0]], norms[bad[0]]
        if norm < 1e-12:
            raise DatasetError(f"{where}: zero quaternion; expected a unit quaternion in {layout}")
        raise DatasetError(f"{where}: quaternion norm is {norm:.6f}; expected a unit quaternion "
                           f"(norm 1 within {QUAT_NORM_TOL:g}) in {layout}")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    if len(values):
        poses[:, :3, :3] = quat_xyzw_to_rotation(values[:, 3:7] / norms[:, None])
        poses[:, :3, 3] = values[:, :3]
    return poses


def read_cameras(path: str | Path) -> dict[str, Camera]:
    """Read ``cameras.json`` (camera id -> camera dict); DatasetError naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"missing {path}: expected a JSON object mapping camera ids to "
                           "camera dicts (Camera.to_dict())")
    try:
        data = json.loads(_read_text(path))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg})") from exc
    if not isinstance(data, dict) or not data:
        raise DatasetError(f"{path}: expected a non-empty JSON object mapping camera ids to "
                           f"camera dicts, got {type(data).__name__}"
                           + (" (empty)" if isinstance(data, dict) else ""))
    cameras = {}
    for camera_id, camera_dict in data.items():
        problem = camera_id_problem(camera_id)
        if problem:
            raise DatasetError(f"{path}: {problem}")
        try:
            cameras[camera_id] = camera_from_dict(camera_dict)
        except CameraError as exc:
            raise DatasetError(f"{path}: camera {camera_id!r}: {exc}") from exc
    return cameras


def read_camera_json(path: str | Path) -> Camera:
    """One camera from a JSON file holding either a camera dict or a ``cameras.json`` with
    exactly one camera (for ``--camera-json``)."""
    path = Path(path)
    try:
        data = json.loads(_read_text(path))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg})") from exc
    if isinstance(data, dict) and "model" not in data and len(data) == 1:
        ((_, data),) = data.items()
    try:
        return camera_from_dict(data)
    except CameraError as exc:
        raise DatasetError(f"{path}: expected a camera dict (Camera.to_dict()) or a "
                           f"cameras.json with one camera: {exc}") from exc


def read_pose_file(path: str | Path, *, cameras: Mapping[str, Camera]) -> list[DatasetEntry]:
    """Read ``map.txt`` / ``queries.txt`` lines ``<image> <camera id> tx ty tz qx qy qz qw``;
    DatasetError naming file and line for a malformed line, an unknown camera id or an image
    listed twice."""
    path = Path(path)
    rows: list[tuple[str, str]] = []
    values: list[Array] = []
    wheres: list[str] = []
    first_line: dict[str, int] = {}
    for lineno, tokens in iter_data_lines(path):
        where = f"{path}:{lineno}"
        if len(tokens) != 9:
            raise DatasetError(f"{where}: expected 9 fields '{POSE_LINE}', got "
                               f"{len(tokens)}{_spaces_hint(tokens, 9)}")
        image_path, camera_id = _checked_path(tokens[0], where), tokens[1]
        if camera_id not in cameras:
            raise DatasetError(f"{where}: unknown camera id {camera_id!r}; expected one of "
                               f"{sorted(cameras)} from {CAMERAS_FILE}")
        if image_path in first_line:
            raise DatasetError(f"{where}: duplicate image path {image_path!r} (first listed "
                               f"on line {first_line[image_path]}); expected each image once")
        first_line[image_path] = lineno
        rows.append((image_path, camera_id))
        values.append(parse_numbers(tokens[2:], where, "tx ty tz qx qy qz qw"))
        wheres.append(where)
    poses = poses_from_rows(np.array(values), wheres)
    return [DatasetEntry(image, camera_id, pose)
            for (image, camera_id), pose in zip(rows, poses, strict=True)]


def read_depth_file(path: str | Path, *,
                    image_paths: Iterable[str]) -> dict[str, tuple[str, float]]:
    """Read ``depth.txt`` (or ``truth_depth.txt``) lines ``<image> <depth png> <metres per
    unit>``; every image must be one of ``image_paths`` (map or queries), listed once, and
    metres per unit must be positive."""
    path = Path(path)
    known = set(image_paths)
    depth: dict[str, tuple[str, float]] = {}
    for lineno, tokens in iter_data_lines(path):
        where = f"{path}:{lineno}"
        if len(tokens) != 3:
            raise DatasetError(f"{where}: expected 3 fields '{DEPTH_LINE}', got "
                               f"{len(tokens)}{_spaces_hint(tokens, 3)}")
        image_path = _checked_path(tokens[0], where)
        depth_path = _checked_path(tokens[1], where)
        (metres_per_unit,) = parse_numbers(tokens[2:], where, "metres per unit")
        if image_path not in known:
            raise DatasetError(f"{where}: depth for {image_path!r}, which is not listed in "
                               f"{MAP_FILE} or {QUERIES_FILE}")
        if image_path in depth:
            raise DatasetError(f"{where}: second depth map for {image_path!r}; expected one")
        if metres_per_unit <= 0:
            raise DatasetError(f"{where}: metres per unit is {metres_per_unit}; expected a "
                               "positive number (0.0002 for 5000 units per metre)")
        depth[image_path] = (depth_path, float(metres_per_unit))
    return depth


def read_dataset(root: str | Path) -> Dataset:
    """Read and validate the dataset in folder ``root`` (images are not opened)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} does not exist or is not a folder")
    cameras = read_cameras(root / CAMERAS_FILE)
    if not (root / MAP_FILE).is_file():
        raise DatasetError(f"missing {root / MAP_FILE}: expected one line '{POSE_LINE}' per "
                           "map keyframe")
    map_entries = read_pose_file(root / MAP_FILE, cameras=cameras)
    query_entries = (read_pose_file(root / QUERIES_FILE, cameras=cameras)
                     if (root / QUERIES_FILE).is_file() else [])
    image_paths = [e.image_path for e in map_entries + query_entries]
    depth, truth_depth = ((read_depth_file(root / name, image_paths=image_paths)
                           if (root / name).is_file() else {})
                          for name in (DEPTH_FILE, TRUTH_DEPTH_FILE))
    calibration = (read_calibration_sigma(root / CALIBRATION_FILE)
                   if (root / CALIBRATION_FILE).is_file() else None)
    return Dataset(root, cameras, map_entries, query_entries, depth, truth_depth, calibration)


def read_calibration_sigma(path: str | Path) -> tuple[float, float]:
    """``calibration.json``'s (relative focal, radial pixels) 1-sigma calibration accuracy;
    DatasetError naming the file unless it is an object with exactly those two finite,
    non-negative numbers."""
    path = Path(path)
    try:
        data = json.loads(_read_text(path))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not JSON ({exc}); {_CALIBRATION_EXPECTED}") from None
    if not isinstance(data, dict) or sorted(data) != sorted(CALIBRATION_KEYS):
        raise DatasetError(f"{path}: {_CALIBRATION_EXPECTED}, got {data!r}")
    return checked_calibration([data[key] for key in CALIBRATION_KEYS], str(path))


_CALIBRATION_EXPECTED = ('expected {"focal_sigma_rel": <relative focal, >= 0>, '
                         '"radial_sigma_px": <pixels at the farthest corner, >= 0>}')


def checked_calibration(values: Iterable[object], where: str) -> tuple[float, float]:
    """(relative focal, radial pixels) as floats; DatasetError unless both are finite numbers
    >= 0 (a boolean is not a number here)."""
    items = list(values)
    if len(items) != 2 or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            and v >= 0 for v in items):
        raise DatasetError(f"{where}: {_CALIBRATION_EXPECTED}, got {items!r}")
    return float(items[0]), float(items[1])  # type: ignore[arg-type]


# -- helpers ---------------------------------------------------------------------------------

def _spaces_hint(tokens: list[str], expected: int) -> str:
    return " (paths with spaces are not supported)" if len(tokens) > expected else ""


def _checked_path(token: str, where: str) -> str:
    problem = image_path_problem(token)
    if problem:
        raise DatasetError(f"{where}: {problem}")
    return posixpath.normpath(token)


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(f"missing file {path}") from None
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from exc
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from exc



def _decode_image(path: Path, flags: int) -> npt.NDArray[Any]:
    import cv2

    try:
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise DatasetError(f"missing image file {path}") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from exc
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise DatasetError(f"{path}: cannot decode; expected a PNG or JPEG image")
    return image


def _check_size(path: Path, image: npt.NDArray[Any], camera: Camera, camera_id: str) -> None:
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise DatasetError(f"{path}: image is {w}x{h} px, but camera {camera_id!r} expects "
                           f"{camera.width}x{camera.height}")
