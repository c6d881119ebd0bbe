"""A map pool's :class:`~.repetition_index.RepetitionIndex` kept beside a relocalizer's model
in a snapshot, so that loading the map gathers the pool (0.1-0.3 s per 1000 keyframes:
:meth:`LandmarkPool.gather_streamed`, the rows it keeps decoded) and reads its filing
(about 3 MB) instead of training the tree again (3-20 s for the 491k SIFT landmarks of
1000 keyframes).

One ``<kind>.leaves.npz`` per feature kind whose pool is indexed (a pool scanned in full has
nothing to store) under ``repetition/`` of the model directory: the tree and each pool row's
leaf in the narrowest unsigned type (1-2 bytes a row), from which the filing is rebuilt at
load exactly as the build made it (a stable sort by leaf: milliseconds for 491k rows) rather
than stored (4 bytes a row and an offset a leaf, the ``<kind>.npz`` of earlier saves, still
read; a reloc that knows only that name builds the index again, as for any that does not
fit); the snapshot lists it with its size and SHA-256 like every model file, so a damaged
file is refused by name when the map loads.
The file names the descriptors it filed (a digest of the pool's rows) and the options it was
built with: it is used only for the very same pool and options, where it is the index a
build would make (the build is seeded), else the index is built again.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.background import stop_if
from ...core.errors import StorageError
from ...core.map import MapState
from ...core.npz_fields import read_fields
from ..place.vocabulary import VocabularyTree
from .landmark_pool import LandmarkPool
from .map_pool import MapPool
from .repetition_index import IndexConf, RepetitionIndex

#: The folder of a model directory that holds the stored indexes.
STORE_DIR = "repetition"

_TREE_FIELDS = ("centres0", "children0", "centres1", "children1", "n_words", "conf", "digest")
#: The filing as stored: each row's leaf (``<kind>.leaves.npz``), or the order and offsets
#: themselves (``<kind>.npz``, earlier saves).
_FILING_FIELDS = {True: ("leaves",), False: ("order", "offsets")}
#: Stored index file names, newest first: ``<kind>`` + suffix, and whether it holds leaves.
_SUFFIXES = ((".leaves.npz", True), (".npz", False))


#: Bytes hashed between two cancel checks of :func:`pool_digest` (a few milliseconds).
DIGEST_CHUNK_BYTES = 8 << 20


def pool_digest(descriptors: npt.NDArray[Any], cancelled: Callable[[], bool] | None = None
                ) -> npt.NDArray[np.uint8]:
    """(32,) BLAKE2b digest of pool ``descriptors`` (N, D): their shape, type and bytes,
    hashed in chunks with ``cancelled`` checked between them (:func:`stop_if`: a map's
    pool takes about 100 ms to hash)."""
    h = hashlib.blake2b(digest_size=32)
    h.update(f"{descriptors.shape}{descriptors.dtype.str}".encode())
    data = np.ascontiguousarray(descriptors).reshape(-1).view(np.uint8).data
    for start in range(0, len(data), DIGEST_CHUNK_BYTES):
        stop_if(cancelled)
        h.update(data[start:start + DIGEST_CHUNK_BYTES])
    return np.frombuffer(h.digest(), np.uint8).copy()


def _conf_row(conf: IndexConf) -> npt.NDArray[np.int64]:
    return np.array(dataclasses.astuple(conf), np.int64)


def save_index(directory: Path, kind: str, conf: IndexConf, made: MapPool) -> Path | None:
    """Write ``made``'s index as ``directory/repetition/<kind>.npz``; None (nothing written)
    when its pool is scanned in full."""
    tree = made.index.tree
    if tree is None:
        return None
    out = directory / STORE_DIR
    out.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    np.savez(buf, centres0=tree.centres[0], children0=tree.children[0],
             centres1=tree.centres[1], children1=tree.children[1],
             n_words=np.int64(tree.n_words),
             leaves=leaves_of_filing(made.index.order, made.index.offsets),
             conf=_conf_row(conf), digest=pool_digest(made.pool.descriptors))
    path = out / f"{kind}{_SUFFIXES[0][0]}"
    path.write_bytes(buf.getvalue())
    return path


def leaves_of_filing(order: npt.NDArray[np.int32], offsets: npt.NDArray[np.int64]
                     ) -> npt.NDArray[np.unsignedinteger[Any]]:
    """(N,) the leaf of each pool row filed as ``order`` (N,) / ``offsets`` (leaves + 1,), in
    the narrowest unsigned type that holds the leaf ids."""
    n_leaves = len(offsets) - 1
    leaves = np.empty(len(order), np.min_scalar_type(max(n_leaves - 1, 0)))
    leaves[order] = np.repeat(np.arange(n_leaves), np.diff(offsets))
    return leaves


def filing_of_leaves(leaves: npt.NDArray[np.unsignedinteger[Any]], n_leaves: int
                     ) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int64]]:
    """The inverse of :func:`leaves_of_filing`: ``order`` (rows leaf by leaf, ascending
    within a leaf: the stable sort :meth:`RepetitionIndex.build` files them by) and
    ``offsets`` (n_leaves + 1,)."""
    order = np.argsort(leaves, kind="stable").astype(np.int32)
    counts = np.bincount(leaves, minlength=n_leaves)
    return order, np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def _stored_path(directory: Path, kind: str) -> tuple[Path, bool] | None:
    """The stored index file of ``kind`` in ``directory`` (the newest form there) and
    whether it holds leaves; None when there is none."""
    for suffix, leaves in _SUFFIXES:
        path = directory / f"{kind}{suffix}"
        if path.is_file():
            return path, leaves
    return None


def copy_index(source: Path, target: Path, kind: str) -> Path | None:
    """Copy the ``kind`` index stored in model directory ``source`` into model directory
    ``target`` (a save of the very map state ``source`` was loaded as, whose pool was not
    made in this process); None when ``source`` holds none (or no longer exists). Whether
    it still fits is for :func:`load_index` to say, as for any stored index."""
    stored = _stored_path(source / STORE_DIR, kind)
    if stored is None:
        return None
    path = stored[0]
    out = target / STORE_DIR
    out.mkdir(parents=True, exist_ok=True)
    try:
        return Path(shutil.copyfile(path, out / path.name))
    except FileNotFoundError:   # pruned meanwhile: the next load builds it
        return None


def stored_kinds(directory: Path) -> list[str]:
    """Feature kinds with a stored index in model directory ``directory``."""
    return sorted({p.name[:-len(suffix)] for suffix, _ in _SUFFIXES
                   for p in (directory / STORE_DIR).glob(f"*{suffix}")
                   if "." not in p.name[:-len(suffix)]})


def load_index(directory: Path, state: MapState, kind: str, conf: IndexConf,
               cancelled: Callable[[], bool] | None = None) -> MapPool | None:
    """The pool of ``state``'s ``kind`` landmarks with the index stored in model directory
    ``directory``; None when none is stored for ``kind`` or it was built for other rows or
    options (the caller builds it). StorageError naming the file when it is malformed;
    :class:`~reloc_service.core.errors.Cancelled` once ``cancelled()`` is true (checked
    between the file read, each keyframe gathered and the index's checks)."""
    stored = _stored_path(directory / STORE_DIR, kind)
    if stored is None:
        return None
    path, leaves = stored
    arrays = _read(path, leaves)
    if not np.array_equal(arrays["conf"], _conf_row(conf)):
        return None
    ids = list(state.keyframes)
    pool = LandmarkPool.gather_streamed([state.keyframes[k] for k in ids], kind, cancelled)
    stop_if(cancelled)
    if not np.array_equal(arrays["digest"], pool_digest(pool.descriptors, cancelled)):
        return None
    index = _index(path, arrays, pool.descriptors, conf)
    return MapPool(pool, index, ids)


def _read(path: Path, leaves: bool) -> dict[str, npt.NDArray[Any]]:
    """The arrays of stored index ``path`` (``order`` and ``offsets`` made from its leaves
    where it holds them)."""
    arrays = read_fields(path, _TREE_FIELDS + _FILING_FIELDS[leaves],
                         "a stored repetition index")
    if leaves:
        n_words, rows = int(arrays["n_words"]), arrays.pop("leaves")
        if rows.dtype.kind != "u" or rows.ndim != 1 or int(rows.max(initial=0)) >= n_words:
            raise StorageError(f"{path}: expected (N,) unsigned leaf ids below {n_words}, "
                               f"got {rows.shape} {rows.dtype}")
        arrays["order"], arrays["offsets"] = filing_of_leaves(rows, n_words)
    return arrays


def _index(path: Path, a: dict[str, npt.NDArray[Any]], descriptors: npt.NDArray[Any],
           conf: IndexConf) -> RepetitionIndex:
    """The stored index over ``descriptors``, its arrays checked against each other."""
    n_words = int(a["n_words"])
    order, offsets = a["order"], a["offsets"]
    k = a["children0"].shape[-1] if a["children0"].ndim == 2 else -1
    if (a["children0"].shape != (1, k) or a["centres0"].shape[:2] != (1, k)
            or a["children1"].ndim != 2 or a["children1"].shape[1] != k
            or a["centres1"].shape[:2] != a["children1"].shape
            or order.dtype != np.int32 or order.shape != (len(descriptors),)
            or offsets.shape != (n_words + 1,) or offsets[0] != 0
            or offsets[-1] != len(descriptors) or np.any(np.diff(offsets) < 0)
            or int(a["children1"].max(initial=-1)) >= n_words):
        raise StorageError(f"{path}: expected a two-level tree of up to k x k leaves filing "
                           f"{len(descriptors)} rows, got centres {a['centres0'].shape} / "
                           f"{a['centres1'].shape}, {n_words} leaves, {order.shape} rows")
    tree = VocabularyTree((a["centres0"], a["centres1"]),
                          (a["children0"].astype(np.int32), a["children1"].astype(np.int32)),
                          n_words)
    return RepetitionIndex(descriptors, tree, order, offsets.astype(np.int64), conf.branches,
                           conf.leaves)
