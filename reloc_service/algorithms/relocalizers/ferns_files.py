"""The ferns relocalizer's files in a model directory: ``ferns.npz`` (the models' counts and
trained records) and ``ferns.json`` (format version, options, regions). Reading checks the
format version and the options; whether the models fit the map is the models' own check
(:meth:`~reloc_service.algorithms.ferns.models.FernModels.from_files`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.errors import StorageError
from ...core.fileio import atomic_write

FORMAT_VERSION = 1
MODEL_FILE = "ferns.npz"
META_FILE = "ferns.json"


def write_ferns(directory: Path, arrays: dict[str, npt.NDArray[Any]],
                meta: dict[str, Any]) -> None:
    """Write ``arrays`` and ``meta`` (the format version added) into ``directory``."""
    directory = Path(directory)
    # Uncompressed: zlib takes seconds on ~10^7 counts and gains little on the indices.
    atomic_write(directory / MODEL_FILE, lambda f: np.savez(f, **arrays))  # type: ignore[arg-type]
    atomic_write(directory / META_FILE, json.dumps({"format_version": FORMAT_VERSION, **meta}))


def read_ferns(directory: Path, conf: dict[str, Any]
               ) -> tuple[dict[str, npt.NDArray[Any]], dict[str, Any]] | None:
    """(arrays, meta) of what :func:`write_ferns` wrote; None if there is none or if it was
    made with options other than ``conf``; a :class:`StorageError` if the metadata is not
    a ferns model's or its format is newer than this reader."""
    directory = Path(directory)
    if not (directory / META_FILE).exists() or not (directory / MODEL_FILE).exists():
        return None
    try:
        meta = json.loads((directory / META_FILE).read_text())
        version = int(meta["format_version"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise StorageError(f"{directory / META_FILE}: not a ferns model ({exc})") from exc
    if version > FORMAT_VERSION:
        raise StorageError(f"{directory / META_FILE}: format version {version} is newer than "
                           f"this reader's {FORMAT_VERSION}")
    if meta.get("conf") != json.loads(json.dumps(conf)):
        return None
    with np.load(directory / MODEL_FILE) as npz:
        arrays = {k: npz[k] for k in npz.files}
    return arrays, meta
