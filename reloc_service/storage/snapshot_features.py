"""A snapshot's keyframes read back from its feature columns (format 2 and later): each kind's
concatenated fields, widened where stored narrow, sizes from their tables, PQ codes with their
codebook, a keyframe's rows of each; and a keyframe entry's pose covariance and depth."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.cameras import Camera, camera_from_dict
from ..core.errors import CameraError, GeometryError, MapError, StorageError
from ..core.frame import EncodedImage, Features, Keyframe
from ..core.landmark_rows import LANDMARK_ROWS_ONLY
from ..core.landmark_table import LandmarkColumns
from .descriptor_hybrid import EXACT, EXACT_ROWS, EXACT_THRESHOLD, check_exact
from .descriptor_pq import CODEBOOK, DESCRIPTOR_CODES, PQCodebook
from .feature_columns import (
    ANGLELESS_KINDS,
    DERIVABLE_FIELDS,
    EIGHTH_PIXELS,
    LEVEL_PIXELS,
    SCALE_TABLE,
    SIZE_TABLE,
    STORED_FIELDS,
    FeatureColumns,
    LazyFeatures,
)
from .keyframe_parts import LOSSLESS_DEPTH_SUFFIX, absent_image, read_lossless_depth
from .landmark_descriptors import OWN_ROWS, ROW_OF, SHARED_CODES
from .packed_columns import read_column, stored_as
from .snapshot_files import MANIFEST_FILE, SnapshotReader
from .snapshot_format import FEATURE_FIELDS

Array = npt.NDArray[np.float64]


def entry_covariance(entry: Mapping[str, Any]) -> Array | None:
    """The (6, 6) pose covariance of a keyframe entry (checked when the manifest is read), or
    None when the entry has none."""
    value = entry.get("pose_covariance")
    return None if value is None else np.array(value, np.float64)


class FeatureColumnsReader:
    """The memory-mapped feature columns of a format-2 or 3 snapshot, cut into keyframes
    (format 3: narrow columns without derived points, built per keyframe on first use;
    :mod:`.feature_columns`)."""

    def __init__(self, reader: SnapshotReader, manifest: Mapping[str, Any]) -> None:
        kinds = sorted({k for e in manifest["keyframes"] for k in dict(e.get("features", {}))})
        self.lazy = manifest["format_version"] >= 3
        self.columns: dict[str, dict[str, np.ndarray]] = {}
        self._cameras: dict[str, Camera] = {}
        tables: dict[str, np.ndarray] = {}
        scales: dict[str, np.ndarray] = {}
        codebooks: dict[str, PQCodebook] = {}
        for kind in kinds:
            listed = {f for f in (*DERIVABLE_FIELDS, LEVEL_PIXELS, DESCRIPTOR_CODES,
                                  EIGHTH_PIXELS, OWN_ROWS, *ROW_OF, EXACT_ROWS, EXACT)
                      if stored_as(manifest["files"], f"features/{kind}.{f}") is not None}
            stored = [f for f in STORED_FIELDS
                      if not (f == "keypoints_px" and listed & {LEVEL_PIXELS, EIGHTH_PIXELS})
                      and not (f == "descriptors" and listed & {DESCRIPTOR_CODES, *ROW_OF})
                      and not (f == "angles" and manifest["format_version"] >= 6
                               and stored_as(manifest["files"], f"features/{kind}.angles")
                               is None)
                      and not (f == "angles" and manifest["format_version"] >= 4
                               and kind in ANGLELESS_KINDS)]
            fields = [*stored, *sorted(listed)]
            cols = {f: read_column(reader, f"features/{kind}.{f}")
                    for f in (fields if self.lazy else FEATURE_FIELDS)}
            if self.lazy and "sizes" not in cols:
                tables[kind] = _size_table(reader, f"features/{kind}.{SIZE_TABLE}.npy")
            if self.lazy and LEVEL_PIXELS in cols:
                scales[kind] = _size_table(reader, f"features/{kind}.{SCALE_TABLE}.npy")
                if cols[LEVEL_PIXELS].dtype != np.int16 or cols[LEVEL_PIXELS].ndim != 2:
                    raise StorageError(f"{reader.root}/features/{kind}.{LEVEL_PIXELS}.npy: "
                                       f"expected (N, 2) int16, got {cols[LEVEL_PIXELS].shape} "
                                       f"{cols[LEVEL_PIXELS].dtype}")
            codes = cols.get(DESCRIPTOR_CODES, cols.get(SHARED_CODES))
            if codes is not None:
                codebooks[kind] = _codebook(reader, kind, codes, exact=EXACT_ROWS in cols)
                if EXACT_ROWS in cols:
                    _check_exact(reader, kind, cols, len(codes))
            # a shared descriptor column has a row per landmark, not per keypoint; the exact
            # rows' mask a row per code row, their column one per masked row
            lengths = {f: len(c) for f, c in cols.items()
                       if f not in ROW_OF and f not in (EXACT, EXACT_ROWS)}
            if len(set(lengths.values())) != 1:
                raise StorageError(f"{reader.root}/features/{kind}.*.npy: columns of different "
                                   f"lengths {lengths}; expected one row per keypoint")
            # plain ndarray views of the maps: slicing an np.memmap 8000 times (1000 keyframes
            # x 8 columns) paid its __array_finalize__ each time; the views still read the map
            self.columns[kind] = {f: c.view(np.ndarray) for f, c in cols.items()}
        self.shared = FeatureColumns(self.columns, tables, scales, codebooks)
        self.starts: dict[str, list[tuple[int, int]]] = {}

    def attach_landmarks(self, landmarks: LandmarkColumns) -> None:
        """Give the lazily built features the landmark columns (ids and points derived)."""
        starts = {kind: (np.array([p[0] for p in sorted(pairs)], np.int64).reshape(-1),
                         np.array([p[1] for p in sorted(pairs)], np.int64).reshape(-1))
                  for kind, pairs in self.starts.items()}
        try:
            self.shared.attach_landmarks(landmarks, starts)
        except MapError as exc:
            raise StorageError(f"features: {exc}") from exc

    def keyframe(self, reader: SnapshotReader, entry: Mapping[str, Any]) -> Keyframe:
        where = f"{reader.root / MANIFEST_FILE}: keyframe {entry.get('id')!r}"
        try:
            features = self._keyframe_features(int(entry["id"]), dict(entry["features"]))
            camera = self._camera(entry["camera"])
            image = (absent_image(entry) if entry.get("image") is None
                     else EncodedImage(reader.map(entry["image"]), (camera.height, camera.width)))
            if image.shape != (camera.height, camera.width):
                raise ValueError(f"image of {image.shape}, camera of {camera.height}x"
                                 f"{camera.width}")
            depth = _entry_depth(reader, entry)
            timestamp = entry.get("timestamp")
            # held encoded (Frame.image's setter takes an EncodedImage; its type is the pixels)
            kf = Keyframe(image=image, camera=camera,  # type: ignore[arg-type]
                          features=features, id=entry["id"],
                          world_from_cam=np.array(entry["world_from_cam"], np.float64),
                          timestamp=None if timestamp is None else float(timestamp),
                          depth=depth, pose_covariance=entry_covariance(entry))
            if entry.get("landmark_rows_only"):
                kf.cache[LANDMARK_ROWS_ONLY] = True
            return kf
        except StorageError:
            raise
        except (KeyError, TypeError, ValueError, GeometryError, CameraError, MapError) as exc:
            raise StorageError(f"{where}: {exc}") from exc

    def _camera(self, d: Any) -> Camera:
        """``camera_from_dict(d)``, built once per distinct dict: keyframes of one camera
        share a (frozen) Camera instead of rebuilding and revalidating it 1000 times."""
        if not isinstance(d, dict):
            return camera_from_dict(d)
        key = repr(sorted(d.items(), key=lambda kv: str(kv[0])))
        camera = self._cameras.get(key)
        if camera is None:
            camera = self._cameras[key] = camera_from_dict(d)
        return camera

    def _keyframe_features(self, kf_id: int, entry: Mapping[str, Any]
                           ) -> dict[str, Features] | LazyFeatures:
        rows = {kind: self._rows(kind, r) for kind, r in entry.items()}
        for kind, (start, _) in rows.items():
            self.starts.setdefault(kind, []).append((kf_id, start))
        if self.lazy:
            return LazyFeatures(self.shared, rows)
        return {kind: Features(kind=kind, **self.shared.raw(kind, *r)) for kind, r in rows.items()}

    def _rows(self, kind: str, rows: Any) -> tuple[int, int]:
        start, stop = (int(r) for r in rows)
        if kind not in self.columns:
            raise ValueError(f"{kind} features listed but not saved")
        n = len(self.columns[kind]["levels"])
        if not 0 <= start <= stop <= n:
            raise ValueError(f"{kind} rows [{start}, {stop}) outside the {n} saved")
        return start, stop


def _entry_depth(reader: SnapshotReader, entry: Mapping[str, Any]) -> np.ndarray | None:
    """A keyframe entry's depth map: None, a raw ``.npy`` (mapped) or a lossless one."""
    rel = entry.get("depth")
    if rel is None:
        return None
    if str(rel).endswith(LOSSLESS_DEPTH_SUFFIX):
        return read_lossless_depth(reader, entry)
    return reader.npy(rel)


def _codebook(reader: SnapshotReader, kind: str, codes: np.ndarray, *, exact: bool = False
              ) -> PQCodebook:
    """The PQ codebook ``kind``'s (N, M) uint8 ``codes`` decode with (checked against them),
    with its exact threshold where its rows keep exact ones (:mod:`.descriptor_hybrid`)."""
    relpath = f"features/{kind}.{CODEBOOK}.npy"
    exact_above = _exact_threshold(reader, kind) if exact else None
    codebook = PQCodebook(np.asarray(reader.npy(relpath)), exact_above=exact_above)
    if codes.dtype != np.uint8 or codes.ndim != 2 or codes.shape[1] != len(codebook.centroids):
        raise StorageError(f"{reader.root}/features/{kind}.{DESCRIPTOR_CODES}.npy: expected "
                           f"(N, {len(codebook.centroids)}) uint8 codes, got {codes.shape} "
                           f"{codes.dtype}")
    return codebook


def _exact_threshold(reader: SnapshotReader, kind: str) -> float:
    """The squared error beyond which ``kind``'s rows were stored exact: a (1,) float64 file."""
    relpath = f"features/{kind}.{EXACT_THRESHOLD}.npy"
    if relpath not in reader.files:
        raise StorageError(f"{reader.root}/features/{kind}.{EXACT_ROWS}: exact rows saved "
                           f"without their threshold {relpath}")
    value = np.asarray(reader.npy(relpath))
    if value.dtype != np.float64 or value.shape != (1,) or not value[0] >= 0:
        raise StorageError(f"{reader.root / relpath}: expected a (1,) float64 threshold >= 0, "
                           f"got {value.shape} {value.dtype}")
    return float(value[0])


def _check_exact(reader: SnapshotReader, kind: str, cols: Mapping[str, np.ndarray],
                 code_rows: int) -> None:
    """StorageError unless ``kind``'s exact-row mask covers its ``code_rows`` code rows and
    its exact column holds one descriptor per masked row."""
    if EXACT not in cols:
        raise StorageError(f"{reader.root}/features/{kind}.{EXACT_ROWS}: saved without "
                           f"{kind}.{EXACT}")
    try:
        check_exact(f"{reader.root}/features/{kind}", np.asarray(cols[EXACT_ROWS]),
                    np.asarray(cols[EXACT]), code_rows)
    except MapError as exc:
        raise StorageError(str(exc)) from exc


def _size_table(reader: SnapshotReader, relpath: str) -> np.ndarray:
    """A (K, 2) float32 table of (level ascending, value): sizes or scales by level."""
    table = np.asarray(reader.npy(relpath))
    if table.ndim != 2 or table.shape[1] != 2 or table.dtype != np.float32 or np.any(
            np.diff(table[:, 0]) <= 0):
        raise StorageError(f"{reader.root / relpath}: expected a (K, 2) float32 table of "
                           f"(level ascending, value), got {table.shape} {table.dtype}")
    return table
