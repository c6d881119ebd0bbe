"""Pure request handlers: wire bytes in, wire bytes out (or a :class:`ProtocolError`).

Nothing here knows about Zenoh. Each handler decodes strictly (``reloc_client.protocol``),
converts to the core types (:mod:`.codec`: grey image, :class:`Camera`, ``world_from_cam``),
calls the map's runtime and encodes the answer; the Zenoh layer sends a failure as
:func:`.codec.error_reply`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Protocol

import cv2
import numpy as np
import numpy.typing as npt
from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, ProtocolError
from reloc_client.result import reply_from_result

from ..algorithms.relocalizers.base import Prior, RelocResult
from ..core.cameras import Camera
from ..core.foreground import answering
from ..core.frame import Frame
from ..core.map import MapState
from .codec import CameraRegistry, decode_image, pose_covariance_to_wire, resolve_camera

if TYPE_CHECKING:
    from .runtime import MapRuntime


# -- relocalize -------------------------------------------------------------------------------

class QueryMap(CameraRegistry, Protocol):
    """What answering a relocalize query needs of a map: the service's :class:`MapRuntime`,
    or a worker process's replica (:class:`.processes.ReplicaMap`)."""

    def cameras(self) -> dict[str, Camera]: ...

    def map_state(self) -> MapState: ...

    def check_method(self, method: str | None) -> str: ...

    def relocalize(self, frame: Frame, *, method: str, prior: Prior | None,
                   hypotheses: int) -> RelocResult: ...


def check_query_camera(rt: QueryMap, camera: Camera, path: str) -> None:
    """An inline query camera may be no larger (in pixels) than the map's largest known
    camera: a query costs about 215 bytes of peak memory per pixel (measured, sbi/bow), so a
    4096x4096 query against a VGA map would cost 3.6 GB. A map with no camera yet is bounded
    by ``limits.max_image_pixels`` alone (checked when the request was decoded)."""
    largest = _largest_known_camera(rt)
    if largest is None or camera.width * camera.height <= largest[0] * largest[1]:
        return
    raise ProtocolError(ErrorCode.IMAGE_TOO_LARGE,
                        f"{path}: {camera.width}x{camera.height} = "
                        f"{camera.width * camera.height} px; expected at most the map's largest "
                        f"known camera, {largest[0]}x{largest[1]} = {largest[0] * largest[1]} "
                        f"px (or name a camera of the map with camera_id)")


def _largest_known_camera(rt: QueryMap) -> tuple[int, int] | None:
    """(width, height) of the registered or keyframe camera with the most pixels."""
    sizes = [cam.size for cam in rt.cameras().values()]
    sizes += [kf.camera.size for kf in rt.map_state().keyframes.values()]
    return max(sizes, key=lambda wh: wh[0] * wh[1], default=None)


def relocalize(rt: MapRuntime, payload: bytes, *, queued_s: float = 0.0) -> bytes:
    """RelocalizeRequest bytes -> RelocalizeReply bytes (ProtocolError for a bad request)."""
    reply, ok, total = relocalize_reply(rt, payload, queued_s=queued_s)
    rt.stats.record_relocalize(ok, total)
    return reply


def relocalize_reply(rt: QueryMap, payload: bytes, *, queued_s: float = 0.0
                     ) -> tuple[bytes, bool, float]:
    """(RelocalizeReply bytes, relocalized, total seconds) for RelocalizeRequest bytes on
    ``rt`` (a map runtime or a worker process's replica: name, limits, cameras, methods,
    map state, relocalize); ProtocolError for a bad request. Records no statistics (the
    service's map runtime keeps them)."""
    with answering():   # from the decode on: background work steps aside for all of it
        return _relocalize_reply(rt, payload, queued_s)


def _relocalize_reply(rt: QueryMap, payload: bytes, queued_s: float
                      ) -> tuple[bytes, bool, float]:
    start = time.perf_counter()
    request = wire.RelocalizeRequest.decode(payload, rt.limits)
    camera = resolve_camera(rt, request.camera_id, request.camera, "relocalize")
    if request.camera is not None:
        check_query_camera(rt, camera, "relocalize.camera")
    image = decode_image(request.image, camera, "relocalize.image")
    method = rt.check_method(request.method)
    prior = None
    if request.prior is not None:
        covariance = request.prior.covariance
        prior = Prior(request.prior.world_from_cam.matrix(), request.prior.radius_m,
                      None if covariance is None else np.reshape(covariance, (6, 6)))
    frame = Frame(image, camera)
    decoded = time.perf_counter()
    result = rt.relocalize(frame, method=method, prior=prior, hypotheses=request.hypotheses)
    timings = {**result.timings, "decode": decoded - start, "queue": queued_s}
    timings["total"] = time.perf_counter() - start + queued_s
    answer = replace(result, timings=timings, request_id=request.request_id,
                     timestamp=request.timestamp)
    return reply_from_result(answer).encode(), result.ok, timings["total"]


def camera_not_replayed(rt: MapRuntime, payload: bytes) -> ProtocolError:
    """BUSY for RelocalizeRequest bytes whose ``camera_id`` the map did not know while its
    journal replayed: the camera may be put in the records not replayed yet, so "never put"
    would be wrong, and BUSY is what a client retries (UNKNOWN_CAMERA it takes as final)."""
    camera_id = wire.RelocalizeRequest.decode(payload, rt.limits).camera_id
    return ProtocolError(ErrorCode.BUSY,
                         f"relocalize.camera_id: camera {camera_id!r} is not on map "
                         f"{rt.name!r} yet: {rt.replay_note()}, and the camera may be put in "
                         "the records not replayed yet; retry in a few seconds (the map's "
                         "status says replaying until its journal is replayed)")


def busy_reply(reason: str) -> bytes:
    """A RelocalizeReply with status ``busy`` (the queue is full)."""
    return wire.RelocalizeReply(wire.ReplyStatus.BUSY, reason=reason).encode()


# -- train, status ----------------------------------------------------------------------------

def train(rt: MapRuntime, payload: bytes) -> bytes:
    """TrainRequest bytes -> TrainReply bytes; the job runs in the background.

    An empty payload is refused: a bare ``get <prefix>/**`` (a discovery or a typo) must not
    start training and a snapshot on every map (docs/protocol.md, TrainRequest)."""
    if not payload:
        raise ProtocolError(ErrorCode.MISSING_FIELD,
                            "train: expected a TrainRequest payload (at least {\"v\": 1}); an "
                            "empty payload is not a train request")
    request = wire.TrainRequest.decode(payload, rt.limits)
    method = None if request.method is None else rt.check_method(request.method)
    job_id, started = rt.start_training(method)
    reason = "" if started else "a training job is already running; follow its events"
    return wire.TrainReply(accepted=True, job_id=job_id, reason=reason).encode()


def status(rt: MapRuntime, payload: bytes, *, content_hash: bool = False,
           counters: Mapping[str, int] | None = None) -> bytes:
    """Empty payload -> StatusReply bytes (with the map's content hash if asked, and the
    service-wide ``counters`` beside the map's own: its memory budget's)."""
    if payload:
        wire.unpack_message(payload, rt.limits)  # a payload is not expected, but a valid one is OK
    return with_counters(rt.status(content_hash=content_hash), counters).encode()


def with_counters(reply: wire.StatusReply, counters: Mapping[str, int] | None
                  ) -> wire.StatusReply:
    """``reply`` with ``counters`` added to its own."""
    return reply if not counters else replace(reply, counters={**reply.counters, **counters})


# -- map copying ------------------------------------------------------------------------------

def keyframe_infos(rt: MapRuntime, *, images: bool) -> list[tuple[int, bytes]]:
    """(keyframe id, KeyframeInfo bytes) of every keyframe, in the order they were added to
    the map (a replica replays them in that order: see replication.Bootstrap); with ``images``, each
    carries its image as PNG."""
    state = rt.map_state()
    out = []
    for kf_id in state.keyframes:
        kf = state.keyframes[kf_id]
        image = _png(kf.image) if images else None
        info = wire.KeyframeInfo(
            id=kf_id, camera=wire.WireCamera.from_dict(kf.camera.to_dict()),
            world_from_cam=wire.WirePose.from_matrix(kf.world_from_cam),
            camera_id=rt.keyframe_camera_id(kf_id), timestamp=kf.timestamp,
            num_landmarks=int(sum(int(f.has_landmark.sum()) for f in kf.features.values())),
            image=image, pose_covariance=pose_covariance_to_wire(kf.pose_covariance))
        out.append((kf_id, info.encode()))
    return out


def camera_puts(rt: MapRuntime) -> list[tuple[str, bytes]]:
    """(camera id, CameraPut bytes) of every registered camera."""
    return [(cid, wire.CameraPut(cid, wire.WireCamera.from_dict(cam.to_dict())).encode())
            for cid, cam in sorted(rt.cameras().items())]


def _png(image: npt.NDArray[np.uint8]) -> wire.WireImage:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding of a keyframe image failed")
    return wire.WireImage.from_bytes(buf.tobytes())
