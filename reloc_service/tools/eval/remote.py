"""The ``--remote`` backend of ``reloc eval``: the map is uploaded to a running service through
:class:`reloc_client.RelocClient`, trained there, and every query is answered over Zenoh.

The scores are computed exactly as in-process (:func:`~.evaluate.evaluate` does the scoring,
and the client answers the same :class:`~reloc_client.result.RelocResult` as the engine);
only where the work runs differs. Plugin options are the service's own configuration (its
TOML ``[options]``), so none can be passed here; the methods must be ones the service serves.
"""

from __future__ import annotations

import queue
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from reloc_client import protocol as wire
from reloc_client.client import NoReplyError, RelocClient, ServiceBusy, ServiceError

from ...algorithms.relocalizers.base import RelocResult
from ...core.cameras import Camera
from ...core.errors import ConfigError, RelocError
from .backends import LandmarkSource, RemoteSpec

Array = npt.NDArray[np.float64]

#: Retries of a query the service answered "busy" (with a growing pause).
BUSY_RETRIES = 50


class RemoteError(RelocError):
    """The service refused a keyframe or a query, or did not answer."""


def make_remote_backend(remote: RemoteSpec, *, methods: Sequence[str],
                        options: Mapping[str, Any], landmark_source: LandmarkSource
                        ) -> RemoteBackend:
    """A :class:`RemoteBackend` on ``remote`` (the seam :func:`~.evaluate.evaluate` calls)."""
    if options:
        raise ConfigError(f"--options cannot be applied to a remote service (its TOML [options] "
                          f"configure it); got {sorted(options)}")
    return RemoteBackend(remote, methods, landmark_source)


class RemoteBackend:
    """Upload, train and query through a service (see module docstring). The map named in
    ``remote`` is emptied first, then holds the dataset's keyframes (ids = map.txt rows)."""

    def __init__(self, remote: RemoteSpec, methods: Sequence[str],
                 landmark_source: LandmarkSource) -> None:
        self.remote = remote
        self.landmark_source = landmark_source
        self.description = f"remote {remote.endpoint} map {remote.map_name}"
        self.client = RelocClient(remote.endpoint, map=remote.map_name, timeout=remote.timeout_s)
        self._events: queue.Queue[wire.Event] = queue.Queue()
        self._cameras: dict[Camera, str] = {}
        self.methods = list(methods)
        try:
            served = self._served_methods()
            if served is not None:
                self._check_methods(served)
            self._subscriber = self.client.subscribe_events(
                self._events.put, kinds=[wire.EventKind.KEYFRAME_ADDED,
                                         wire.EventKind.KEYFRAME_REMOVED,
                                         wire.EventKind.KEYFRAME_REJECTED,
                                         wire.EventKind.CAMERA_ADDED,
                                         wire.EventKind.CAMERA_REJECTED])
            time.sleep(0.2)  # let the subscription reach the service before the first put
            if self._map_exists:
                self._clear_map()
        except Exception:
            self.client.close()
            raise

    def _served_methods(self) -> list[str] | None:
        """The methods the service serves, from this map's status, or from another map of
        the service when this one does not exist yet (the first put creates it); None when the
        service serves no map yet."""
        self._map_exists = False
        try:
            methods = list(self.client.status(timeout=3.0).methods)
            self._map_exists = True
            return methods
        except NoReplyError:
            live = self.client.maps(timeout=2.0)
        if not live:
            return None
        other = RelocClient(self.remote.endpoint, map=live[0][1], timeout=self.remote.timeout_s)
        try:
            return list(other.status(timeout=3.0).methods)
        finally:
            other.close()

    def _check_methods(self, served: Sequence[str]) -> None:
        missing = [m for m in self.methods if m not in served]
        if missing:
            raise ConfigError(f"the service at {self.remote.endpoint} does not serve {missing} "
                              f"on map {self.remote.map_name!r}; it serves {list(served)}")

    def _clear_map(self) -> None:
        for info in self.client.keyframes(timeout=self.remote.timeout_s):
            self.client.remove_keyframe(info.id)
            self._wait_for(wire.EventKind.KEYFRAME_REMOVED, info.id)

    # -- Backend ---------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, image: npt.NDArray[np.uint8], camera: Camera,
                     world_from_cam: Array, *, depth: npt.NDArray[np.float32] | None,
                     pose_covariance: Array | None = None) -> None:
        """Put the keyframe and wait until the service has applied it."""
        camera_id = self._camera_id(camera)
        self.client.add_keyframe(kf_id, image, world_from_cam, camera_id=camera_id,
                                 depth=None if depth is None else np.asarray(depth),
                                 pose_covariance=pose_covariance)
        self._wait_for(wire.EventKind.KEYFRAME_ADDED, kf_id)

    def _camera_id(self, camera: Camera) -> str:
        if camera not in self._cameras:
            camera_id = f"cam{len(self._cameras)}"
            self.client.set_camera(camera_id, camera)
            self._wait_for(wire.EventKind.CAMERA_ADDED, camera_id)
            if not self._map_exists:  # created by this put: now its methods can be read
                self._check_methods(self.client.status().methods)
                self._map_exists = True
            self._cameras[camera] = camera_id
        return self._cameras[camera]

    def _wait_for(self, kind: wire.EventKind, ident: Any) -> None:
        """Block until the event ``kind`` for ``ident`` (RemoteError on its rejection)."""
        rejected = (wire.EventKind.CAMERA_REJECTED if kind is wire.EventKind.CAMERA_ADDED
                    else wire.EventKind.KEYFRAME_REJECTED)
        deadline = time.monotonic() + max(self.remote.timeout_s, 60.0)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise RemoteError(f"the service did not report {kind.value} for {ident!r} "
                                  f"within {max(self.remote.timeout_s, 60.0):.0f} s")
            try:
                event = self._events.get(timeout=remaining)
            except queue.Empty:
                continue
            if event.fields.get("id") != ident:
                continue
            if event.kind is kind:
                return
            if event.kind is rejected:
                raise RemoteError(f"the service rejected {ident!r}: "
                                  f"{event.fields.get('code')}: {event.fields.get('message')}")

    def train(self, *, progress: bool) -> None:
        """Train every served method and wait for ``train_done``."""
        try:
            self.client.train(wait=True, timeout=3600.0)
        except ServiceError as exc:
            raise RemoteError(f"training on the service failed: {exc}") from exc

    def relocalize(self, image: npt.NDArray[np.uint8], camera: Camera, *, method: str,
                   gt_world_from_cam: Array) -> RelocResult:
        """One query over Zenoh (retried while the service is busy); the client's result is
        the relocalizer's own type, so it is scored as it comes."""
        camera_id = self._camera_id(camera)
        for attempt in range(BUSY_RETRIES):
            try:
                return self.client.relocalize(image, camera_id=camera_id, method=method)
            except ServiceBusy:
                time.sleep(min(0.05 * (attempt + 1), 1.0))
            except ServiceError as exc:
                raise RemoteError(f"the service refused a query: {exc}") from exc
        raise RemoteError(f"the service stayed busy for {BUSY_RETRIES} attempts")

    def map_counts(self) -> tuple[int, int]:
        status = self.client.status()
        return status.keyframes, status.landmarks

    def landmark_errors_m(self, dataset: Any) -> Array | None:
        """Unknown: landmark positions do not travel over the protocol."""
        return None

    def close(self) -> None:
        sub = getattr(self, "_subscriber", None)
        if sub is not None:
            try:
                sub.undeclare()
            except Exception:
                pass
        self.client.close()

