"""What :func:`~.evaluate.evaluate` needs of the place where the work runs: the
:class:`Backend` protocol, the :class:`LandmarkSource` option and the :class:`RemoteSpec` of a
service.

A module of its own, below both ``evaluate`` (which drives a backend) and ``remote`` (which
implements one), so that neither imports the other's module for these types.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

from ...algorithms.relocalizers.base import RelocResult
from ...core.cameras import Camera

if TYPE_CHECKING:
    from ..data.dataset import Dataset

Array = npt.NDArray[np.float64]


class LandmarkSource(enum.Enum):
    """Where the map's landmarks come from: ``auto`` lifts keypoints with the dataset's depth
    where a keyframe has a depth map and triangulates the rest (what the service does with
    keyframes that carry depth); ``triangulate`` ignores depth maps; ``depth`` requires one
    for every keyframe."""

    AUTO = "auto"
    TRIANGULATE = "triangulate"
    DEPTH = "depth"

    def uses_depth(self) -> bool:
        return self is not LandmarkSource.TRIANGULATE


@dataclass(frozen=True)
class RemoteSpec:
    """Evaluate through a running service: Zenoh ``endpoint`` (e.g. ``tcp/127.0.0.1:7447``)
    and the name of the map to upload into."""

    endpoint: str
    map_name: str
    timeout_s: float = 30.0


class Backend(Protocol):
    """Where the map is built and the queries are answered (in-process or a remote service).

    Keyframe ids are the rows of ``map.txt`` (0-based); results must name matched keyframes
    by those ids."""

    #: Human-readable description (``"in-process"``, ``"remote tcp/...:7447 map desk"``).
    description: str

    def add_keyframe(self, kf_id: int, image: npt.NDArray[np.uint8], camera: Camera,
                     world_from_cam: Array, *, depth: npt.NDArray[np.float32] | None,
                     pose_covariance: Array | None = None) -> None:
        """Add one posed keyframe (and its landmarks) to the map; ``pose_covariance`` (6, 6)
        says how well ``world_from_cam`` is known (None: the map's default)."""

    def train(self, *, progress: bool) -> None:
        """Train every method's models on the whole map; return when done."""

    def relocalize(self, image: npt.NDArray[np.uint8], camera: Camera, *, method: str,
                   gt_world_from_cam: Array) -> RelocResult:
        """Answer one query with ``method``; ``gt_world_from_cam`` is only for the
        evaluation-only ``gt`` place finder."""

    def map_counts(self) -> tuple[int, int]:
        """(keyframes, landmarks) in the map."""

    def landmark_errors_m(self, dataset: Dataset) -> Array | None:
        """(L,) landmark position errors (metres) against ground truth, or None if unknown."""

    def close(self) -> None:
        """Release what the backend holds (sessions, threads)."""

