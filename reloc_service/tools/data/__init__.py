"""Datasets: the reloc dataset v1 folder format and converters from TUM RGB-D and EuRoC MAV.

Names are re-exported lazily, so importing :mod:`reloc_service.tools.data.cli` (for ``reloc --help``)
does not load NumPy, SciPy or OpenCV.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {
    "Dataset": "dataset",
    "DatasetEntry": "dataset",
    "read_dataset": "dataset",
    "write_dataset": "dataset_write",
    "read_pose_file": "dataset",
    "write_pose_file": "dataset_write",
    "read_cameras": "dataset",
    "read_camera_json": "dataset",
    "convert_tum": "tum",
    "convert_euroc": "euroc",
}

__all__ = [
    "Dataset",
    "DatasetEntry",
    "convert_euroc",
    "convert_tum",
    "read_camera_json",
    "read_cameras",
    "read_dataset",
    "read_pose_file",
    "write_dataset",
    "write_pose_file",
]

if TYPE_CHECKING:
    from .dataset import (
        Dataset,
        DatasetEntry,
        read_camera_json,
        read_cameras,
        read_dataset,
        read_pose_file,
    )
    from .dataset_write import write_dataset, write_pose_file
    from .euroc import convert_euroc
    from .tum import convert_tum


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
