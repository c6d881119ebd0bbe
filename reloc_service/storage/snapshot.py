"""Map persistence: a whole map saved as an immutable snapshot directory, switched atomically.

Layout of a map directory ``MAP`` (format version 8; a snapshot that shares no descriptor
between a landmark's rows is written as format 7, which it then is)::

    MAP/CURRENT                     names the current snapshot: ``snapshots/000012``
    MAP/snapshots/000012/
        manifest.json               format, versions, keyframes, and a SHA-256 of every file
        images/<id>.jpg|png         keyframe images: the JPEG (or grey PNG) a client sent, as
                                    sent; else the pixels as PNG (decoded when first used);
                                    only where a method reads them or the owner asks (else
                                    the manifest keeps their size and CRC-32: format 5,
                                    :mod:`.keyframe_parts`)
        depth/<id>.npy|.f32.zlib    float32 Z-depth maps, raw or zlib-compressed, only when
                                    the owner asks: they are an input to landmark creation,
                                    done when the keyframe was added (format 5)
        features/<kind>.<field>.npy every keyframe's features of one kind, concatenated in
                                    manifest order (each keyframe names its row range); narrow
                                    where lossless, no field load can derive exactly (points
                                    and ids from the landmarks, ORB sizes from the levels, ORB
                                    keypoints from int16 pixels of their level; keypoint
                                    angles, read by nothing, not at all): see
                                    :mod:`.feature_columns`;
                                    SIFT descriptors as PQ codes + codebook, keypoints in
                                    1/8 px where the owner asks (format 6,
                                    :mod:`.descriptor_pq`), and a keyframe's
                                    keypoints with a landmark only where it asks and the map's
                                    methods allow (its entry says ``landmark_rows_only``:
                                    :mod:`.landmark_rows`), and one descriptor (or code) a
                                    landmark where it asks (``landmark_descriptors``, format
                                    8: :mod:`.landmark_descriptors`)
        thumbnails/<key>.npy        small blurry images already computed (one row a keyframe;
                                    float16 in a compact save, format 6)
        landmarks/<column>.npy      landmark ids, points, depth sigmas, observations (CSR):
                                    integers in the narrowest exact type, points as float32
                                    offsets from an observing keyframe where the rounding is
                                    far below each landmark's uncertainty (see
                                    :mod:`.landmark_codec`), else float64
        models/<method>/...         whatever each relocalizer's ``save(dir)`` wrote; a file
                                    equal to another method's (the same trained model) is a
                                    hard link to it: its bytes are on disk once

A column of ``features/`` or ``landmarks/`` that zlib shrinks to a quarter or less (ids,
observation offsets, kinds and keyframes, pyramid levels, constant sigmas) is stored as
``<column>.npy.zlib`` or ``<column>.delta.npy.zlib`` instead of ``.npy`` and decompressed at
load (format 7, :mod:`.packed_columns`).

Every array is a plain ``.npy`` that :func:`load_map` memory-maps read-only (the images too,
decoded by the keyframe on first use): loading rebuilds nothing but each kind's landmark ids
(one scatter of the observations) and the landmark integer columns stored narrower than they
are held (one vectorised copy each; float32 points and sigmas stay mapped unless packed, their float64 rows
decoded on read), the arrays stay on disk until a query touches them (each keyframe's features
are built from the shared columns on first use), and a change after loading copies what it
changes (copy on write; the snapshot files are never written again). Each file's SHA-256 is
checked at load (streamed, so a check does not hold the file in memory). Snapshots of format
version 7 (one descriptor a keypoint), 6 (every column a ``.npy``), 5 (every keypoint, SIFT
descriptors, keypoints and angles in full), 4 (every image and depth map, depth raw), 3
(float64 landmark points, float32 ORB keypoints and angles), 2 (every feature field in full,
PNG images) and 1 (PNG images, one ``.npz`` per keyframe and kind) are still read.

A save writes a new snapshot (every file fsynced, the manifest last), then replaces
``CURRENT`` with :func:`os.replace` and prunes the snapshots it was built from (keeping the
one it replaced), so a crash at any moment leaves the previous snapshot loadable. A save made
while ``CURRENT`` is missing removes nothing: the snapshots present are not its ancestors.
One process writes a map directory at a time.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from reloc_client.protocol import pose_covariance_problem

from ..core.cameras import camera_from_dict
from ..core.errors import CameraError, GeometryError, MapError, StorageError
from ..core.frame import SIFT_DIM, Features, Keyframe
from ..core.landmark_table import Landmark, LandmarkColumns, LandmarkTable
from ..core.map import MapState
from .feature_columns import (
    feature_count,
)
from .landmark_codec import ANCHORED_POINTS, WidenedColumn, anchored_points
from .packed_columns import read_column, stored_as
from .snapshot_features import FeatureColumnsReader, entry_covariance
from .snapshot_files import (
    CURRENT_FILE,
    MANIFEST_FILE,
    SNAPSHOTS_DIR,
    SnapshotReader,
    current_snapshot,
    switch_current,
)
from .snapshot_format import (
    FEATURE_FIELDS,
    FORMAT,
    FORMAT_VERSION,
    LANDMARK_COLUMNS,
    LANDMARK_DTYPES,
    LANDMARK_FIELDS,
    MODELS_DIR,
    OPTIONAL_LANDMARK_FIELDS,
    READABLE_VERSIONS,
    SHARED_FORMAT_VERSION,
    THUMBNAIL_PREFIX,
    UNSHARED_FORMAT_VERSION,
    model_dir_name,
    thumbnail_path,
)
from .snapshot_save import save_map

#: Saving lives in :mod:`.snapshot_save` and the format's names in :mod:`.snapshot_format`;
#: both are re-exported here, where callers load, save and name snapshots.
__all__ = ["FEATURE_FIELDS", "FORMAT", "FORMAT_VERSION", "LANDMARK_DTYPES", "MODELS_DIR",
           "SHARED_FORMAT_VERSION", "THUMBNAIL_PREFIX", "UNSHARED_FORMAT_VERSION",
           "current_snapshot", "load_map", "model_dir_name", "restore_current", "save_map",
           "saved_models", "snapshot_summary", "verify_snapshot"]

Array = npt.NDArray[np.float64]

# -- reading ----------------------------------------------------------------------------------

def _read_manifest(snapshot: Path) -> dict[str, Any]:
    path = snapshot / MANIFEST_FILE
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StorageError(f"{path}: missing; the snapshot is incomplete") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StorageError(f"{path}: not valid JSON ({exc}); expected the map manifest") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        got = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise StorageError(f"{path}: format {got!r}, expected {FORMAT!r}")
    version = manifest.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise StorageError(f"{path}: format_version {version!r}, expected a positive integer")
    if version > FORMAT_VERSION:
        raise StorageError(f"{path}: written by a newer reloc (format version {version}; this "
                           f"version reads up to {FORMAT_VERSION}); upgrade reloc to load it")
    if version not in READABLE_VERSIONS:
        raise StorageError(f"{path}: format version {version} is not readable by this reloc "
                           f"(it reads {', '.join(map(str, READABLE_VERSIONS))})")
    landmarks_type = str if version == 1 else dict
    for key, kind in (("keyframes", list), ("files", dict), ("models", dict),
                      ("map_version", int), ("next_landmark_id", int),
                      ("landmarks", landmarks_type)):
        if not isinstance(manifest.get(key), kind):
            raise StorageError(f"{path}: field {key!r} missing or not a {kind.__name__}")
    for entry in manifest["keyframes"]:
        _checkentry_covariance(path, entry)
    return manifest


def _checkentry_covariance(path: Path, entry: Any) -> None:
    """A keyframe entry's ``pose_covariance``, when present, must be a pose covariance
    (6x6, finite, symmetric, positive semi-definite); StorageError naming the keyframe."""
    if not isinstance(entry, dict) or entry.get("pose_covariance") is None:
        return
    problem = pose_covariance_problem(entry["pose_covariance"])
    if problem is not None:
        raise StorageError(f"{path}: keyframe {entry.get('id')!r}: pose_covariance: expected a "
                           f"6x6 pose covariance (symmetric, positive semi-definite): {problem}")


def _read_image(reader: SnapshotReader, relpath: str) -> npt.NDArray[np.uint8]:
    data = np.frombuffer(reader.read(relpath), np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 2 or image.dtype != np.uint8:
        raise StorageError(f"{reader.root / relpath}: expected a grey 8-bit PNG")
    return np.asarray(image, dtype=np.uint8)


def _read_keyframe(reader: SnapshotReader, entry: Mapping[str, Any]) -> Keyframe:
    where = f"{reader.root / MANIFEST_FILE}: keyframe {entry.get('id')!r}"
    try:
        features = {}
        for kind, rel in dict(entry["features"]).items():
            arrays = reader.npz(rel, FEATURE_FIELDS)
            arrays["descriptors"] = _compact_descriptors(arrays["descriptors"])
            features[kind] = Features(kind=kind, **arrays)
        depth = None
        if entry.get("depth") is not None:
            depth = np.load(io.BytesIO(reader.read(entry["depth"])), allow_pickle=False)
        timestamp = entry.get("timestamp")
        return Keyframe(image=_read_image(reader, entry["image"]),
                        camera=camera_from_dict(entry["camera"]), features=features,
                        id=entry["id"],
                        world_from_cam=np.array(entry["world_from_cam"], np.float64),
                        timestamp=None if timestamp is None else float(timestamp), depth=depth,
                        pose_covariance=entry_covariance(entry))
    except StorageError:
        raise
    except (KeyError, TypeError, ValueError, GeometryError, CameraError, MapError) as exc:
        raise StorageError(f"{where}: {exc}") from exc


def _compact_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Format-1 SIFT descriptors (float32 holding integers 0-255) as the uint8 kept now;
    anything else (not integral, out of range) unchanged."""
    d = descriptors
    if (d.dtype == np.float32 and d.ndim == 2 and d.shape[1] == SIFT_DIM
            and np.all((d >= 0) & (d <= 255) & (d == np.rint(d)))):
        return d.astype(np.uint8)
    return d


def _read_landmarks(reader: SnapshotReader, relpath: str,
                    keyframes: Mapping[int, Keyframe]) -> dict[int, Landmark]:
    a = reader.npz(relpath, LANDMARK_FIELDS, optional=OPTIONAL_LANDMARK_FIELDS)
    where = reader.root / relpath
    n, n_obs = len(a["ids"]), len(a["obs_keyframe"])
    sigmas = a.get("depth_sigmas_m", np.zeros(n))
    if sigmas.shape != (n,) or not np.all(np.isfinite(sigmas) & (sigmas >= 0)):
        raise StorageError(f"{where}: depth_sigmas_m: expected {n} finite values >= 0")
    offsets = a["obs_offsets"]
    if (a["points_world"].shape != (n, 3) or offsets.shape != (n + 1,) or offsets[0] != 0
            or offsets[-1] != n_obs or np.any(np.diff(offsets) < 0)
            or len(a["obs_kind"]) != n_obs or len(a["obs_keypoint"]) != n_obs):
        raise StorageError(f"{where}: inconsistent landmark arrays (ids {n}, points "
                           f"{a['points_world'].shape}, {n_obs} observations)")
    kinds = [str(k) for k in a["kinds"]]
    _check_observations(where, a, kinds, keyframes)
    obs = list(zip(a["obs_keyframe"].tolist(), [kinds[k] for k in a["obs_kind"].tolist()],
                   a["obs_keypoint"].tolist(), strict=True))
    bounds = offsets.tolist()
    return {lm_id: Landmark(lm_id, a["points_world"][i].copy(),
                            frozenset(obs[bounds[i]:bounds[i + 1]]), float(sigmas[i]))
            for i, lm_id in enumerate(a["ids"].tolist())}


def _check_observations(where: Path, a: Mapping[str, np.ndarray], kinds: list[str],
                        keyframes: Mapping[int, Keyframe]) -> None:
    """Every observation names a saved keyframe, a saved feature kind and a keypoint index."""
    if len(a["obs_kind"]) == 0:
        return
    if a["obs_kind"].min() < 0 or a["obs_kind"].max() >= len(kinds):
        raise StorageError(f"{where}: observation kind index outside {kinds}")
    kf_ids = np.array(sorted(keyframes), dtype=np.int64)
    pos = np.searchsorted(kf_ids, a["obs_keyframe"])
    known = (kf_ids[np.minimum(pos, len(kf_ids) - 1)] == a["obs_keyframe"] if len(kf_ids)
             else np.zeros(len(pos), bool))
    if not known.all():
        unknown = np.unique(a["obs_keyframe"][~known])[:5].tolist()
        raise StorageError(f"{where}: observations of unknown keyframe(s) {unknown}")
    sizes = np.array([[feature_count(keyframes[k].features, kind)
                       if kind in keyframes[k].features else 0
                       for kind in kinds] for k in kf_ids.tolist()], dtype=np.int64)
    size = sizes[pos, a["obs_kind"].astype(np.int64)]
    bad = (a["obs_keypoint"] < 0) | (a["obs_keypoint"] >= size)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise StorageError(f"{where}: observation of keyframe {int(a['obs_keyframe'][i])} "
                           f"{kinds[int(a['obs_kind'][i])]} keypoint {int(a['obs_keypoint'][i])} "
                           f"outside [0, {int(size[i])})")


def _read_keyframes(reader: SnapshotReader, manifest: Mapping[str, Any],
                    read: Callable[[SnapshotReader, Mapping[str, Any]], Keyframe]
                    ) -> dict[int, Keyframe]:
    keyframes: dict[int, Keyframe] = {}
    for entry in manifest["keyframes"]:
        kf = read(reader, entry)
        if kf.id in keyframes:
            raise StorageError(f"{reader.root / MANIFEST_FILE}: keyframe {kf.id} listed twice")
        keyframes[kf.id] = kf
    return keyframes


def _attach_thumbnails(reader: SnapshotReader, manifest: Mapping[str, Any],
                       keyframes: list[Keyframe]) -> None:
    """Put the saved small blurry images back into the keyframes' caches."""
    for key in manifest.get("thumbnails", []):
        stack = reader.npy(thumbnail_path(str(key)))
        if len(stack) != len(keyframes) or stack.ndim != 3:
            raise StorageError(f"{reader.root / thumbnail_path(str(key))}: expected "
                               f"({len(keyframes)}, h, w) thumbnails, got {stack.shape}")
        if stack.dtype == np.float16:   # a compact snapshot's: held float32, as computed
            stack = stack.astype(np.float32)
        for kf, thumb in zip(keyframes, stack, strict=True):
            kf.cache[str(key)] = thumb


def _widened(column: np.ndarray, dtype: Any) -> np.ndarray:
    """``column`` in ``dtype`` (a read-only copy when stored narrower), else as it is."""
    if dtype is None or column.dtype == dtype:
        return column
    wide = column.view(np.ndarray).astype(dtype)
    wide.flags.writeable = False
    return wide


def _read_landmark_columns(reader: SnapshotReader, manifest: Mapping[str, Any],
                           keyframes: Mapping[int, Keyframe]) -> LandmarkColumns:
    meta = manifest["landmarks"]
    where = reader.root / "landmarks"
    anchored = stored_as(manifest["files"], f"landmarks/{ANCHORED_POINTS}") is not None
    a = {name: _widened(read_column(reader, f"landmarks/{name}"), LANDMARK_DTYPES.get(name))
         for name in LANDMARK_COLUMNS if not (anchored and name == "points_world")}
    if anchored:
        a["points_world"] = read_column(reader, f"landmarks/{ANCHORED_POINTS}")
        if a["points_world"].dtype not in (np.float32, np.float16):
            raise StorageError(f"{where}/{ANCHORED_POINTS}.npy: expected float32 or float16, got "
                               f"{a['points_world'].dtype}")
    n, n_obs = len(a["ids"]), len(a["obs_keyframe"])
    offsets = a["obs_offsets"]
    if (a["points_world"].shape != (n, 3) or a["depth_sigmas_m"].shape != (n,)
            or offsets.shape != (n + 1,) or offsets[0] != 0 or offsets[-1] != n_obs
            or len(a["obs_kind"]) != n_obs or len(a["obs_keypoint"]) != n_obs
            or np.any(np.diff(offsets) < 0) or np.any(np.diff(a["ids"]) <= 0)):
        raise StorageError(f"{where}: inconsistent landmark columns (ids {n}, ascending; points "
                           f"{a['points_world'].shape}, {n_obs} observations)")
    kinds = [str(k) for k in meta.get("kinds", [])]
    _check_observations(where, a, kinds, keyframes)
    if anchored:   # float32 (or float16) on disk, float64 rows decoded on read (memory-mapped until then)
        try:
            a["points_world"] = anchored_points(a["points_world"], offsets, a["obs_keyframe"],
                                                keyframes)  # type: ignore[assignment]
        except ValueError as exc:
            raise StorageError(f"{where}/{ANCHORED_POINTS}.npy: {exc}") from exc
    if a["depth_sigmas_m"].dtype == np.float32:
        a["depth_sigmas_m"] = WidenedColumn(a["depth_sigmas_m"])  # type: ignore[assignment]
    return LandmarkColumns(a["ids"], a["points_world"], a["depth_sigmas_m"], offsets,
                           a["obs_keyframe"], a["obs_kind"], a["obs_keypoint"], tuple(kinds))


def load_map(directory: str | Path) -> tuple[MapState, Path | None]:
    """The map saved in ``directory`` and its models directory (None if no model was saved);
    StorageError naming the file if the map is missing, damaged or from a newer version."""
    snapshot = current_snapshot(directory)
    manifest = _read_manifest(snapshot)
    reader = SnapshotReader(snapshot, manifest["files"])
    if manifest["format_version"] == 1:
        keyframes = _read_keyframes(reader, manifest, _read_keyframe)
        landmarks = LandmarkTable.from_mapping(
            _read_landmarks(reader, manifest["landmarks"], keyframes))
    else:
        with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
            try:
                # the columns first (needed before any keyframe), the images behind them
                reader.prefetch(pool, sorted((rel for rel in manifest["files"]
                                              if not rel.startswith(MODELS_DIR + "/")),
                                             key=lambda rel: rel.startswith("images/")))
                columns = FeatureColumnsReader(reader, manifest)
                keyframes = _read_keyframes(reader, manifest, columns.keyframe)
                _attach_thumbnails(reader, manifest, list(keyframes.values()))
                landmark_columns = _read_landmark_columns(reader, manifest, keyframes)
                columns.attach_landmarks(landmark_columns)
                landmarks = LandmarkTable(landmark_columns)
                reader.wait_all()
            finally:
                pool.shutdown(cancel_futures=True)   # a damaged file: do not hash the rest
    state = MapState(MappingProxyType(keyframes), landmarks,
                     manifest["map_version"], manifest["next_landmark_id"])
    models = snapshot / MODELS_DIR
    if not manifest["models"]:
        return state, None
    reader.verify_tree(MODELS_DIR)
    return state, models


def verify_snapshot(snapshot: str | Path) -> int:
    """Check ``snapshot``'s manifest and the size and SHA-256 of every file it lists; the
    number of files checked. StorageError naming the first damaged or missing file."""
    snapshot = Path(snapshot)
    manifest = _read_manifest(snapshot)
    reader = SnapshotReader(snapshot, manifest["files"])
    for rel in manifest["files"]:
        reader.read(rel)
    return len(manifest["files"])


def snapshot_summary(snapshot: str | Path) -> tuple[dict[str, Any], list[int]]:
    """The ``store`` fields (``{}`` for a snapshot saved without them) and the keyframe ids
    of ``snapshot``'s manifest, checked as :func:`load_map` checks it (StorageError)."""
    snapshot = Path(snapshot)
    manifest = _read_manifest(snapshot)
    store = manifest.get("store", {})
    if not isinstance(store, dict):
        raise StorageError(f"{snapshot / MANIFEST_FILE}: field 'store' is not an object")
    try:
        ids = [int(entry["id"]) for entry in manifest["keyframes"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise StorageError(f"{snapshot / MANIFEST_FILE}: a keyframe entry without an integer "
                           f"id ({exc})") from exc
    return store, ids


def restore_current(directory: str | Path, snapshot: str | Path) -> Path:
    """Point a missing ``CURRENT`` of ``directory`` at ``snapshot`` (a name under
    ``snapshots/``) after verifying every file of it; returns the snapshot path.
    StorageError if ``CURRENT`` exists or the snapshot does not verify."""
    directory = Path(directory)
    path = directory / SNAPSHOTS_DIR / Path(snapshot).name
    if (directory / CURRENT_FILE).exists():
        raise StorageError(f"{directory / CURRENT_FILE}: exists; not replaced")
    if not path.is_dir():
        raise StorageError(f"{path}: does not exist")
    verify_snapshot(path)
    switch_current(directory, path)
    return path


def saved_models(directory: str | Path) -> dict[str, Path]:
    """Method string -> model directory of the current snapshot (empty if none)."""
    snapshot = current_snapshot(directory)
    manifest = _read_manifest(snapshot)
    return {method: snapshot / rel for method, rel in manifest["models"].items()}
