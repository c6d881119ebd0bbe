"""What the service's map and a worker process's replica of it share: the write operations
(:class:`WriteOp`), and the query face of a map with the one way a change is applied to it
(:class:`ServedMap`), so that a replica answers a query exactly as the service's map would.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import Any

from reloc_client import protocol as wire

from ..algorithms.relocalizers.base import Prior, RelocResult
from ..core.cameras import Camera
from ..core.frame import Frame
from ..core.map import MapState
from ..engine import Engine
from .codec import KeyframeInput, served_method


class WriteOp(enum.StrEnum):
    """A change to a map: queued in its writer, journaled, forwarded to the worker processes.

    The value is the journal's ``op`` string (the records on disk keep it) and what the pipe
    to a worker process carries (:mod:`.processes` sends ``op.value``, plain data)."""

    KEYFRAME = "kf"      # a keyframe put (added, or replaced under the same id)
    DELETE = "del"       # a keyframe delete
    CAMERA = "cam"       # a camera put (cameras are never deleted)


class ServedMap:
    """A map that answers relocalize queries: its engine, cameras and methods (what
    :class:`.handlers.QueryMap` asks for). The service's :class:`~.runtime.MapRuntime` and a
    worker process's :class:`~.processes.ReplicaMap` are both one."""

    def __init__(self, name: str, engine: Engine, *, limits: wire.Limits,
                 methods: tuple[str, ...], default_method: str,
                 cameras: Mapping[str, Camera] | None = None) -> None:
        self.name = name
        self.engine = engine
        self.limits = limits
        self.methods = methods
        self.default_method = default_method
        self._cameras: dict[str, Camera] = dict(cameras or {})

    def camera(self, camera_id: str) -> Camera | None:
        return self._cameras.get(camera_id)

    def camera_ids(self) -> list[str]:
        return sorted(self._cameras)

    def cameras(self) -> dict[str, Camera]:
        return dict(self._cameras)

    def map_state(self) -> MapState:
        """The map as the relocalizers currently see it."""
        return self.engine.map.snapshot()

    def check_method(self, method: str | None) -> str:
        """``method`` (default: the map's default) if served; UNKNOWN_METHOD otherwise."""
        return served_method(self.name, self.methods, self.default_method, method)

    def relocalize(self, frame: Frame, *, method: str, prior: Prior | None,
                   hypotheses: int) -> RelocResult:
        return self.engine.relocalize(frame, method=method, prior=prior, hypotheses=hypotheses)

    def apply_change(self, op: WriteOp, *args: Any) -> None:
        """Apply a validated change: ``KEYFRAME, kf_input`` builds the keyframe into the engine
        (its features and landmarks computed from the input, so the same inputs in the same
        order give the same map in the service and in every replica), ``DELETE, kf_id``
        removes it, ``CAMERA, camera_id, camera`` registers the camera."""
        if op is WriteOp.KEYFRAME:
            kf: KeyframeInput = args[0]
            self.engine.add_keyframe(kf.kf_id, kf.image, kf.camera, kf.world_from_cam,
                                     **kf.engine_kwargs())
        elif op is WriteOp.DELETE:
            self.engine.remove_keyframe(args[0])
        elif op is WriteOp.CAMERA:
            camera_id, camera = args
            self._cameras[camera_id] = camera
        else:
            raise ValueError(f"unknown map change {op!r}")
