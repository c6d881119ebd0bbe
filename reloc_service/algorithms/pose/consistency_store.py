"""Each keyframe's held-out statistic (:mod:`.map_consistency`) kept beside a relocalizer's
model in a snapshot, so that the first queries of a loaded map read it instead of computing
it (the keyframe's landmarks re-triangulated without it and its intrinsics tested on them:
tens to hundreds of milliseconds a keyframe and feature kind, paid by whichever query first
lands near it).

One ``<kind>.npz`` per feature kind under ``consistency/`` of the model directory: per
keyframe, the digest of what its statistic was computed from (:class:`InputsDigest`), its
plain and gated ``T^2`` and its cells' variance components, each marked computed or not and
None or not. The snapshot lists the file with its size and SHA-256 like every model file, so a
damaged one is refused by name when the map loads; a reloc that does not know the folder
loads the model without it (a model's loader reads the files it names) and computes the
statistics, as before they were stored.
An entry is used only where the loaded map's inputs for its keyframe have its digest: the same
held-out landmarks, observed at the same pixels by the same keyframes at the same poses
through the same cameras, and the same options. There a computation gives the stored values
bit for bit, but where landmarks lifted from depth maps are read: their points count in the
form a snapshot stores them (rounded within 1/100 of their uncertainty), and the values are
those the saving engine computed on them unrounded. Any other keyframe computes its own, as
without a store.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.errors import StorageError
from ...core.npz_fields import read_fields
from ...core.triangulation import ViewObservations
from .cell_correlation import CellComponents

#: The folder of a model directory that holds the stored statistics.
STORE_DIR = "consistency"
#: The layout of a stored file; a newer one is refused (it may mean something else).
FILE_VERSION = 1
SUFFIX = ".npz"
DIGEST_BYTES = 32

_FIELDS = ("version", "keyframe_ids", "digests", "values", "value_status", "cells",
           "cell_status")
#: A value's status in a stored file: not computed, computed as None, computed.
NOT_COMPUTED, NONE, COMPUTED = 0, 1, 2
#: The statistics' order in a stored row: plain (False), then gated (True).
_ROBUST = (False, True)


@dataclasses.dataclass(frozen=True)
class KeyframeStatistics:
    """What computing one keyframe's statistic gave and the digest of its inputs:
    ``values`` the plain (False) and gated (True) ``T^2`` computed (None: too few held-out
    landmarks), ``cells`` its cells' variance components where ``has_cells`` says they were
    computed (None: too few)."""

    digest: bytes
    values: Mapping[bool, float | None]
    has_cells: bool = False
    cells: CellComponents | None = None

    def merged(self, newer: KeyframeStatistics) -> KeyframeStatistics:
        """``newer``, with what this one computed from the same inputs and it did not."""
        if newer.digest != self.digest:
            return newer
        has_cells = newer.has_cells or self.has_cells
        return KeyframeStatistics(self.digest, {**self.values, **newer.values}, has_cells,
                                  newer.cells if newer.has_cells else self.cells)


class InputsDigest:
    """A BLAKE2b digest (:data:`DIGEST_BYTES`) of what a statistic is computed from, fed
    part by part: texts with their length, arrays with their shape and type, so that two
    different sequences of parts never feed the same bytes."""

    def __init__(self, name: str) -> None:
        self._hash = hashlib.blake2b(digest_size=DIGEST_BYTES)
        self.text(name)

    def text(self, text: str) -> None:
        data = text.encode()
        self._hash.update(len(data).to_bytes(8, "little"))
        self._hash.update(data)

    def array(self, array: npt.ArrayLike) -> None:
        values = np.ascontiguousarray(array)
        self.text(f"{values.shape}{values.dtype.str}")
        self._hash.update(values.tobytes())

    def camera(self, camera: Camera) -> None:
        """The camera as saved with the map (its model and every parameter)."""
        self.text(json.dumps(camera.to_dict(), sort_keys=True))

    def view(self, view: ViewObservations) -> None:
        """One view's camera, pose and observations (points, pixels and their noise)."""
        self.camera(view.camera)
        self.array(np.asarray(view.cam_from_world, np.float64))
        self.array(np.asarray(view.point_index, np.int64))
        self.array(np.asarray(view.pixels_px, np.float64))
        self.array(np.asarray(view.sigmas, np.float64))

    def digest(self) -> bytes:
        return self._hash.digest()


def write_statistics(directory: Path, kind: str, entries: Mapping[int, KeyframeStatistics]
                     ) -> Path | None:
    """Write ``entries`` (keyframe id -> its ``kind`` statistics) as
    ``directory/consistency/<kind>.npz``; None (nothing written) when there are none."""
    if not entries:
        return None
    ids = sorted(entries)
    rows = [entries[k] for k in ids]
    values = np.full((len(ids), len(_ROBUST)), np.nan)
    value_status = np.zeros((len(ids), len(_ROBUST)), np.int8)
    cells = np.full((len(ids), 3), np.nan)
    cell_status = np.zeros(len(ids), np.int8)
    for i, row in enumerate(rows):
        for j, robust in enumerate(_ROBUST):
            value_status[i, j], values[i, j] = _status(robust in row.values,
                                                       row.values.get(robust))
        if row.has_cells and row.cells is not None:
            cell_status[i] = COMPUTED
            cells[i] = (row.cells.between_mean_square, row.cells.within_mean_square,
                        row.cells.n0)
        elif row.has_cells:
            cell_status[i] = NONE
    buf = io.BytesIO()
    np.savez(buf, version=np.int64(FILE_VERSION), keyframe_ids=np.array(ids, np.int64),
             digests=np.array([np.frombuffer(r.digest, np.uint8) for r in rows], np.uint8),
             values=values, value_status=value_status, cells=cells, cell_status=cell_status)
    out = directory / STORE_DIR
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{kind}{SUFFIX}"
    path.write_bytes(buf.getvalue())
    return path


def _status(computed: bool, value: float | None) -> tuple[int, float]:
    if not computed:
        return NOT_COMPUTED, np.nan
    return (NONE, np.nan) if value is None else (COMPUTED, float(value))


def stored_kinds(directory: Path) -> list[str]:
    """Feature kinds with stored statistics in model directory ``directory``."""
    return sorted(p.name[:-len(SUFFIX)] for p in (directory / STORE_DIR).glob(f"*{SUFFIX}")
                  if "." not in p.name[:-len(SUFFIX)])


def read_statistics(directory: Path, kind: str) -> dict[int, KeyframeStatistics]:
    """The ``kind`` statistics stored in model directory ``directory`` (keyframe id -> its
    entry; empty when none are stored). StorageError naming the file when it is not what
    :func:`write_statistics` writes."""
    path = directory / STORE_DIR / f"{kind}{SUFFIX}"
    if not path.is_file():
        return {}
    a = _read(path)
    ids = a["keyframe_ids"]
    return {int(k): KeyframeStatistics(
                a["digests"][i].tobytes(),
                {robust: _value(a["value_status"][i, j], a["values"][i, j])
                 for j, robust in enumerate(_ROBUST) if a["value_status"][i, j] != NOT_COMPUTED},
                bool(a["cell_status"][i] != NOT_COMPUTED),
                CellComponents(*(float(v) for v in a["cells"][i]))
                if a["cell_status"][i] == COMPUTED else None)
            for i, k in enumerate(ids.tolist())}


def _value(status: np.integer[Any], value: np.floating[Any]) -> float | None:
    return None if status == NONE else float(value)


def _read(path: Path) -> dict[str, npt.NDArray[Any]]:
    """The arrays of stored statistics ``path``, their shapes and codes checked."""
    a = read_fields(path, _FIELDS, "stored keyframe statistics")
    if a["version"].shape != () or int(a["version"]) > FILE_VERSION:
        raise StorageError(f"{path}: layout version {a['version']}, expected at most "
                           f"{FILE_VERSION} (written by a newer reloc)")
    n = len(a["keyframe_ids"])
    expected = {"keyframe_ids": ((n,), "i"), "digests": ((n, DIGEST_BYTES), "u"),
                "values": ((n, 2), "f"), "value_status": ((n, 2), "i"),
                "cells": ((n, 3), "f"), "cell_status": ((n,), "i")}
    for name, (shape, dtype_kind) in expected.items():
        if a[name].shape != shape or a[name].dtype.kind != dtype_kind:
            raise StorageError(f"{path}: {name}: expected {shape} of kind {dtype_kind!r} for "
                               f"{n} keyframes, got {a[name].shape} {a[name].dtype}")
    codes = np.concatenate([a["value_status"].ravel(), a["cell_status"]])
    if len(np.unique(a["keyframe_ids"])) != n or not np.isin(codes, (0, 1, 2)).all():
        raise StorageError(f"{path}: expected distinct keyframe ids and status codes "
                           f"{NOT_COMPUTED}, {NONE} or {COMPUTED}")
    return a
