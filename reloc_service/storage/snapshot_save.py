"""Writing a map snapshot (:func:`save_map`): every file of a new snapshot directory, the
manifest last, then ``CURRENT`` switched to it (layout and crash safety: :mod:`.snapshot`'s
docstring; reading it back: :mod:`.snapshot`)."""

from __future__ import annotations

import io
import json
import os
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ..core.absent_image import AbsentImage
from ..core.errors import StorageError
from ..core.fileio import fsync_path
from ..core.frame import Keyframe
from ..core.landmark_table import LandmarkColumns
from ..core.map import MapState
from .descriptor_hybrid import EXACT_ROWS, EXACT_THRESHOLD
from .descriptor_pq import CODEBOOK
from .feature_columns import (
    feature_count,
    narrowest,
)
from .keyframe_parts import (
    EVERYTHING,
    StoredParts,
    depth_file,
    image_entry,
)
from .kind_columns import codebook_for, kind_columns
from .landmark_codec import encode_geometry
from .landmark_descriptors import OWN_ROWS
from .landmark_rows import (
    SHARED_MODES,
    RowMasks,
    kept_count,
    landmark_rows_only,
    renumber_observations,
    row_masks,
)
from .landmark_summary import kept_landmarks
from .packed_columns import packed_file
from .snapshot_files import (
    MANIFEST_FILE,
    SnapshotWriter,
    current_or_none,
    fsync_tree,
    new_snapshot_dir,
    prune_snapshots,
    switch_current,
)
from .snapshot_format import (
    EXACT_ROWS_FORMAT_VERSION,
    FORMAT,
    HALF_POINTS_FORMAT_VERSION,
    LANDMARK_INTEGERS,
    LANDMARK_NARROWER,
    MODELS_DIR,
    OWN_ROWS_FORMAT_VERSION,
    SHARED_FORMAT_VERSION,
    THUMBNAIL_PREFIX,
    UNSHARED_FORMAT_VERSION,
    model_dir_name,
    thumbnail_path,
)

#: Writes one method's trained model into the (empty) directory it is given.
ModelWriter = Callable[[Path], None]


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def _image_file(kf: Keyframe) -> tuple[str, bytes]:
    """``kf``'s image file (extension, bytes): the compressed image it was given (a client's
    JPEG, a loaded snapshot's file: never re-encoded, and a lossy one not made lossier), else
    its pixels as PNG."""
    if kf.encoded is not None:
        return kf.encoded.format, kf.encoded.tobytes()
    return "png", _png_bytes(kf.image)


def _png_bytes(image: npt.NDArray[np.uint8]) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise StorageError("could not encode a keyframe image as PNG")
    return buf.tobytes()


def _write_keyframe(writer: SnapshotWriter, kf: Keyframe, rows: Mapping[str, tuple[int, int]],
                    parts: StoredParts) -> dict[str, Any]:
    """The manifest entry of ``kf`` (its image and depth written as ``parts`` says, where
    ``parts.images == "always"`` means stored; features by row range)."""
    entry: dict[str, Any] = {
        "id": kf.id, "camera": kf.camera.to_dict(), "world_from_cam": kf.world_from_cam.tolist(),
        "timestamp": None if kf.timestamp is None else float(kf.timestamp),
        "depth": None, "features": {k: list(r) for k, r in sorted(rows.items())}}
    if parts.images == "always" and not isinstance(kf.image_source, AbsentImage):
        ext, data = _image_file(kf)
        entry["image"] = writer.write(f"images/{kf.id}.{ext}", data)
    else:   # not kept, or a loaded map's keyframe that has none: its size and checksum
        entry.update(image_entry(kf))
    if kf.pose_covariance is not None:   # absent: none was put (older snapshots neither)
        entry["pose_covariance"] = kf.pose_covariance.tolist()
    if kf.depth is not None and parts.depth == "raw":
        entry["depth"] = writer.write(f"depth/{kf.id}.npy", _npy_bytes(kf.depth.astype(np.float32)))
    elif kf.depth is not None and (compressed := depth_file(kf.id, kf.depth, parts.depth)):
        entry["depth"] = writer.write(*compressed)
    return entry


def _feature_rows(keyframes: list[Keyframe], masks: RowMasks
                  ) -> dict[int, dict[str, tuple[int, int]]]:
    """Per keyframe id, per kind, its row range in the concatenated feature columns (the
    rows ``masks`` keeps)."""
    ends: dict[str, int] = {}
    out: dict[int, dict[str, tuple[int, int]]] = {}
    for kf in keyframes:
        out[kf.id] = {}
        for kind in sorted(kf.features):
            start = ends.get(kind, 0)
            ends[kind] = start + kept_count(masks, kf.id, kind,
                                            feature_count(kf.features, kind))
            out[kf.id][kind] = (start, ends[kind])
    return out


def _write_features(writer: SnapshotWriter, keyframes: list[Keyframe], state: MapState,
                    landmarks: LandmarkColumns,
                    rows: Mapping[int, Mapping[str, tuple[int, int]]], codec: str,
                    masks: RowMasks, shared: bool, medoid: bool = False) -> None:
    """One ``.npy`` per kind and stored column (:func:`.kind_columns.kind_columns`; the
    rows ``masks`` keeps; ``shared``: one descriptor per landmark, its rows' medoid's with
    ``medoid``), and the codebook of a
    kind whose descriptors are PQ codes."""
    for kind in sorted({k for kf in keyframes for k in kf.features}):
        owners = [(kf.id, rows[kf.id][kind][0], kf.features)
                  for kf in keyframes if kind in kf.features]
        codebook = codebook_for(kind, owners, codec,
                                [kf.cache for kf in keyframes if kind in kf.features])
        if codebook is not None:
            writer.write(f"features/{kind}.{CODEBOOK}.npy", _npy_bytes(codebook.centroids))
        if codebook is not None and codebook.exact_above is not None:
            writer.write(f"features/{kind}.{EXACT_THRESHOLD}.npy",
                         _npy_bytes(np.array([codebook.exact_above], np.float64)))
        keep = [masks.get((kf_id, kind)) for kf_id, _, _ in owners]
        for name, column in kind_columns(kind, owners, state.landmarks, landmarks,
                                         codebook, keep, compact=codec != "none",
                                         shared=shared, medoid=medoid).items():
            writer.write(*packed_file(f"features/{kind}.{name}", column))


def _write_thumbnails(writer: SnapshotWriter, keyframes: list[Keyframe], compact: bool
                      ) -> list[str]:
    """Small blurry images every keyframe already has (same cache key), one file per key;
    ``compact``: float16 (zero-mean blurred grey levels within +-255: rounded by at most
    1/16 of a grey level, noise far below the image's own), else float32 as held."""
    if not keyframes:
        return []
    keys = set.intersection(*({k for k in kf.cache if k.startswith(THUMBNAIL_PREFIX)}
                              for kf in keyframes))
    dtype = np.float16 if compact else np.float32
    for key in sorted(keys):
        stack = np.stack([np.asarray(kf.cache[key], np.float32) for kf in keyframes]).astype(dtype)
        writer.write(thumbnail_path(key), _npy_bytes(stack))
    return sorted(keys)


def _write_landmarks(writer: SnapshotWriter, columns: LandmarkColumns,
                     keyframes: Mapping[int, Keyframe], *, exact: bool, half: bool
                     ) -> tuple[dict[str, Any], bool]:
    """The landmark columns: ids and observation indices in the narrowest exact integer
    type, points and sigmas float32 (points float16 with ``half``) where
    :func:`encode_geometry` allows (never if ``exact``). Returns the manifest's entry and
    whether the points were stored float16."""
    for name in LANDMARK_INTEGERS:
        column = narrowest(np.asarray(getattr(columns, name)), LANDMARK_NARROWER[name])
        writer.write(*packed_file(f"landmarks/{name}", column))
    geometry = encode_geometry(columns, keyframes, exact=exact, half=half)
    for name, column in geometry.items():
        writer.write(*packed_file(f"landmarks/{name}", column))
    halved = any(column.dtype == np.float16 for column in geometry.values())
    return {"dir": "landmarks", "kinds": list(columns.kinds), "count": len(columns.ids)}, halved


def save_map(state: MapState, directory: str | Path, *,
             models: Mapping[str, ModelWriter] | None = None,
             exact_geometry: bool = False, store: Mapping[str, Any] | None = None,
             parts: StoredParts = EVERYTHING) -> Path:
    """Save ``state`` (and models: method -> writer called with its own empty directory) as a
    new snapshot of map directory ``directory``; returns the snapshot path. With
    ``exact_geometry`` landmark points and sigmas are stored float64 as held (a replica that
    must answer bit for bit as this map does), else float32 where far below their
    uncertainty (:func:`.landmark_codec.encode_geometry`). ``store``: what the map's owner
    records about it (identity, last sequence number held), kept as the manifest's
    ``store``. ``parts``: what is stored of each keyframe's depth and image
    (:class:`.keyframe_parts.StoredParts`; images only with ``images="always"``, the caller
    having decided whether its methods need them; default: everything, raw). A save that
    fails (a full disk, ...) removes its partial snapshot directory: the space it took is
    given back and ``CURRENT`` still names the previous snapshot."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    previous = current_or_none(directory)
    snapshot = new_snapshot_dir(directory)
    try:
        _write_snapshot(state, snapshot, models or {}, exact_geometry, store or {}, parts)
    except BaseException:
        shutil.rmtree(snapshot, ignore_errors=True)   # nothing refers to it yet
        raise
    switch_current(directory, snapshot)
    prune_snapshots(directory, snapshot, previous)
    return snapshot


def _write_snapshot(state: MapState, snapshot: Path, models: Mapping[str, ModelWriter],
                    exact_geometry: bool, store: Mapping[str, Any], parts: StoredParts) -> None:
    """Every file of a new snapshot, the manifest last, fsynced with their directories."""
    writer = SnapshotWriter(snapshot)
    # insertion order, kept by load_map: a replica copies the map in the order it was built
    kfs = list(state.keyframes.values())
    held = state.landmarks.columns()
    kept = None   # every landmark, or a summary map's (:mod:`.landmark_summary`)
    if parts.landmark_budget > 0:
        held = held.select(kept_landmarks(kfs, held, parts.landmark_budget))
        kept = np.asarray(held.ids, np.int64)
    masks = row_masks(kfs, parts.descriptors, kept)
    rows = _feature_rows(kfs, masks)
    keyframes = [_write_keyframe(writer, kf, rows[kf.id], parts) for kf in kfs]
    for entry, only in zip(keyframes, landmark_rows_only(kfs, masks), strict=True):
        if only:
            entry["landmark_rows_only"] = True
    columns = renumber_observations(held, masks)
    shared = parts.descriptors in SHARED_MODES
    _write_features(writer, kfs, state, columns, rows, parts.descriptor_codec, masks,
                    shared=shared, medoid=parts.descriptors == "per-landmark-medoid")
    thumbnails = _write_thumbnails(writer, kfs, compact=parts.descriptor_codec != "none")
    landmarks, half_points = _write_landmarks(writer, columns, state.keyframes, exact=exact_geometry,
                                 half=parts.landmark_points == "float16")
    model_dirs: dict[str, str] = {}
    for method, write_model in models.items():
        rel = f"{MODELS_DIR}/{model_dir_name(method)}"
        (snapshot / rel).mkdir(parents=True, exist_ok=True)
        write_model(snapshot / rel)
        writer.record_tree(rel)
        model_dirs[method] = rel
    link_duplicate_models(snapshot, writer.files)
    manifest = {"format": FORMAT,
                "format_version": _format_version(shared, writer.files, half_points),
                "map_version": int(state.version), "next_landmark_id": int(state.next_landmark_id),
                "keyframes": keyframes, "landmarks": landmarks, "thumbnails": thumbnails,
                "models": model_dirs, "store": dict(store),
                "files": writer.files}
    writer.write(MANIFEST_FILE, json.dumps(manifest, indent=1).encode("utf-8"))
    fsync_tree(snapshot)
    fsync_path(snapshot.parent)


def link_duplicate_models(snapshot: Path, files: Mapping[str, Mapping[str, Any]]) -> int:
    """Make each model file of ``snapshot`` whose bytes equal an earlier one's (two methods
    holding the same trained model: the default chain's bow step and ``bow+p3p`` train the
    same seeded vocabulary on the same map) a hard link to it, so the disk holds those bytes
    once; every method still reads its own path and the manifest (sizes, SHA-256) is as
    written. ``files``: the manifest's entries. Returns the bytes no longer stored twice
    (0 where the file system makes no hard links: the copies stay)."""
    first: dict[tuple[str, int], Path] = {}
    saved = 0
    for rel, entry in sorted(files.items()):
        if not rel.startswith(MODELS_DIR + "/") or entry["size"] == 0:
            continue
        key, path = (entry["sha256"], entry["size"]), snapshot / rel
        if key not in first:
            first[key] = path
            continue
        link = path.with_name(path.name + ".link")
        try:
            os.link(first[key], link)
        except OSError:
            continue
        os.replace(link, path)
        saved += entry["size"]
    return saved


def _format_version(shared: bool, files: Mapping[str, Any], half_points: bool) -> int:
    """The oldest format that reads what was written: 11 with exact descriptor rows beside
    PQ codes (:mod:`.descriptor_hybrid`), 10 with float16 landmark points, 9 with own-row
    masks (:data:`.landmark_descriptors.OWN_ROWS`), 8 with shared descriptors, else 7."""
    if any(f".{EXACT_ROWS}." in name for name in files):
        return EXACT_ROWS_FORMAT_VERSION
    if half_points:
        return HALF_POINTS_FORMAT_VERSION
    if not shared:
        return UNSHARED_FORMAT_VERSION
    own = any(f".{OWN_ROWS}." in name for name in files)
    return OWN_ROWS_FORMAT_VERSION if own else SHARED_FORMAT_VERSION

