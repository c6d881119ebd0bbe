"""Pure request handlers: wire bytes in, wire bytes out (or a :class:`ProtocolError`).

Nothing here knows about Zenoh. Each handler decodes strictly (``reloc_client.protocol``),
converts to the core types (:mod:`.codec`: grey image, :class:`Camera`, ``world_from_cam``),
calls the map's runtime and encodes the answer; the Zenoh layer sends a failure as
:func:`.codec.error_reply`.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt
from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, ProtocolError

from ..cameras import Camera
from ..frame import Frame
from ..relocalizers.base import Prior, RelocResult
from .codec import Array, decode_image, resolve_camera

if TYPE_CHECKING:
    from .runtime import MapRuntime


# -- relocalize -------------------------------------------------------------------------------

def check_query_camera(rt: MapRuntime, camera: Camera, path: str) -> None:
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


def _largest_known_camera(rt: MapRuntime) -> tuple[int, int] | None:
    """(width, height) of the registered or keyframe camera with the most pixels."""
    sizes = [cam.size for cam in rt.cameras().values()]
    sizes += [kf.camera.size for kf in rt.map_state().keyframes.values()]
    return max(sizes, key=lambda wh: wh[0] * wh[1], default=None)


def relocalize(rt: MapRuntime, payload: bytes, *, queued_s: float = 0.0) -> bytes:
    """RelocalizeRequest bytes -> RelocalizeReply bytes (ProtocolError for a bad request)."""
    start = time.perf_counter()
    request = wire.RelocalizeRequest.decode(payload, rt.limits)
    camera = resolve_camera(rt, request.camera_id, request.camera, "relocalize")
    if request.camera is not None:
        check_query_camera(rt, camera, "relocalize.camera")
    image = decode_image(request.image, camera, "relocalize.image")
    method = rt.check_method(request.method)
    prior = None
    if request.prior is not None:
        prior = Prior(request.prior.world_from_cam.matrix(), request.prior.radius_m)
    frame = Frame(image, camera)
    decoded = time.perf_counter()
    result = rt.relocalize(frame, method=method, prior=prior, hypotheses=request.hypotheses)
    timings = {**result.timings, "decode": decoded - start, "queue": queued_s}
    timings["total"] = time.perf_counter() - start + queued_s
    reply = reply_from_result(result, timings, request)
    rt.stats.record_relocalize(result.ok, timings["total"])
    return reply.encode()


def reply_from_result(result: RelocResult, timings: dict[str, float],
                      request: wire.RelocalizeRequest | None = None) -> wire.RelocalizeReply:
    """The wire reply for an engine result (non-finite optional numbers are left out)."""
    ok = result.ok and result.world_from_cam is not None
    return wire.RelocalizeReply(
        status=wire.ReplyStatus.OK if ok else wire.ReplyStatus.NOT_RELOCALIZED,
        method=result.method,
        world_from_cam=wire.WirePose.from_matrix(result.world_from_cam) if ok else None,
        covariance=_covariance(result.covariance) if ok else None,
        confidence=float(np.clip(result.confidence, 0.0, 1.0)) if ok else 0.0,
        inliers=max(int(result.inliers), 0), num_matches=max(int(result.num_matches), 0),
        reprojection_rms_px=_finite_or_none(result.reprojection_rms_px),
        matched_keyframe_ids=tuple(int(k) for k in result.matched_keyframe_ids if k >= 0),
        map_version=max(int(result.map_version), 0),
        timings={k: float(v) for k, v in timings.items() if np.isfinite(v) and v >= 0},
        reason="" if ok else (result.reason or "not relocalized"),
        hypotheses=tuple(_hypothesis(h) for h in result.hypotheses if h.ok),
        request_id=None if request is None else request.request_id,
        timestamp=None if request is None else request.timestamp)


def busy_reply(reason: str) -> bytes:
    """A RelocalizeReply with status ``busy`` (the queue is full)."""
    return wire.RelocalizeReply(wire.ReplyStatus.BUSY, reason=reason).encode()


def _hypothesis(h: RelocResult) -> wire.Hypothesis:
    assert h.world_from_cam is not None
    return wire.Hypothesis(
        world_from_cam=wire.WirePose.from_matrix(h.world_from_cam), method=h.method,
        confidence=float(np.clip(h.confidence, 0.0, 1.0)), inliers=max(int(h.inliers), 0),
        num_matches=max(int(h.num_matches), 0),
        reprojection_rms_px=_finite_or_none(h.reprojection_rms_px),
        covariance=_covariance(h.covariance),
        matched_keyframe_ids=tuple(int(k) for k in h.matched_keyframe_ids if k >= 0))


def _covariance(covariance: Array | None) -> tuple[float, ...] | None:
    if covariance is None:
        return None
    c = np.asarray(covariance, dtype=np.float64)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)):
        return None
    return tuple(float(v) for v in c.ravel())


def _finite_or_none(x: float | None) -> float | None:
    if x is None or not np.isfinite(x) or x < 0:
        return None
    return float(x)


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


def status(rt: MapRuntime, payload: bytes) -> bytes:
    """Empty payload -> StatusReply bytes."""
    if payload:
        wire.unpack_message(payload, rt.limits)  # a payload is not expected, but a valid one is OK
    return rt.status().encode()


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
            image=image)
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
