"""Named arrays read from a NumPy ``.npz`` file that reloc wrote beside a model: every field
asked for, or a :class:`~.errors.StorageError` that names the file and what it should hold."""

from __future__ import annotations

import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .errors import StorageError


def read_fields(path: Path, fields: Sequence[str], what: str) -> dict[str, npt.NDArray[Any]]:
    """The arrays ``fields`` of ``path`` read into memory (no pickled objects); StorageError
    where the file is not a readable ``.npz`` or lacks a field, saying it should be ``what``
    (e.g. "a stored repetition index")."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            missing = [f for f in fields if f not in npz.files]
            if missing:
                raise StorageError(f"{path}: expected {what} with {', '.join(fields)}; "
                                   f"missing {', '.join(missing)}")
            return {f: npz[f] for f in fields}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise StorageError(f"{path}: not readable as {what} ({exc})") from exc
