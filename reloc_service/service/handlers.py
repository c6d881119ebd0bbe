"""Pure request handlers: wire bytes in, wire bytes out (or a :class:`ProtocolError`).

Nothing here knows about Zenoh. Each handler decodes strictly (``reloc_client.protocol``),
converts to the core types (grey image, :class:`Camera`, ``world_from_cam``), calls the map's
runtime and encodes the answer. :func:`error_of` turns any exception into the protocol's
error code and message, so the Zenoh layer only has to send it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt
from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, ProtocolError
from reloc_client.result import reply_from_result

from ..cameras import Camera, camera_from_dict
from ..errors import (
    CameraError,
    ConfigError,
    GeometryError,
    MapError,
    NotTrainedError,
    StorageError,
)
from ..frame import Frame
from ..relocalizers.base import Prior

if TYPE_CHECKING:
    from .runtime import MapRuntime

log = logging.getLogger(__name__)

Array = npt.NDArray[np.float64]


class CameraRegistry(Protocol):
    """What decoding a request needs of a map: its name, limits and known cameras."""

    name: str
    limits: wire.Limits

    def camera(self, camera_id: str) -> Camera | None: ...

    def camera_ids(self) -> list[str]: ...


# -- errors -----------------------------------------------------------------------------------

def error_of(exc: BaseException) -> tuple[ErrorCode, str]:
    """The protocol error code and message for ``exc`` (unexpected ones are INTERNAL)."""
    if isinstance(exc, ProtocolError):
        return exc.code, exc.message
    for kind, code in _ERROR_CODES:
        if isinstance(exc, kind):
            return code, str(exc)
    log.error("internal error", exc_info=exc)
    return ErrorCode.INTERNAL, f"{type(exc).__name__}: {exc}"


_ERROR_CODES: tuple[tuple[type[BaseException], ErrorCode], ...] = (
    (NotTrainedError, ErrorCode.NOT_TRAINED),
    (StorageError, ErrorCode.STORAGE_ERROR), (CameraError, ErrorCode.BAD_CAMERA),
    (MapError, ErrorCode.UNKNOWN_KEYFRAME), (GeometryError, ErrorCode.BAD_VALUE),
    (ConfigError, ErrorCode.UNKNOWN_METHOD))


def error_reply(exc: BaseException) -> bytes:
    """The payload of the Zenoh error reply for ``exc``."""
    code, message = error_of(exc)
    return wire.encode_error(code, message)


# -- conversions wire -> core -----------------------------------------------------------------

def to_camera(camera: wire.WireCamera, path: str = "camera") -> Camera:
    """A core camera from a validated wire camera; BAD_CAMERA if the model refuses it."""
    try:
        return camera_from_dict(camera.to_dict())
    except CameraError as exc:
        raise ProtocolError(ErrorCode.BAD_CAMERA, f"{path}: {exc}") from None


def decode_image(image: wire.WireImage, camera: Camera, path: str) -> npt.NDArray[np.uint8]:
    """(H, W) uint8 grey pixels of ``image``; BAD_IMAGE if it does not decode or its size is
    not the camera's."""
    if (image.width, image.height) != camera.size:
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}: size {image.width}x{image.height} does not match the "
                            f"camera's {camera.width}x{camera.height}")
    if image.format is wire.ImageFormat.MONO8:
        return image.to_array()
    _check_header_size(image, camera, path)
    grey = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}.data: the {image.format.value} data does not decode")
    if grey.shape != (image.height, image.width):
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}: decodes to {grey.shape[1]}x{grey.shape[0]}, stated "
                            f"{image.width}x{image.height}")
    return np.asarray(grey, dtype=np.uint8)


def _check_header_size(image: wire.WireImage, camera: Camera, path: str) -> None:
    """The PNG IHDR / JPEG SOF size must be the camera's before ``cv2.imdecode`` allocates
    what the header declares (a 16 KB PNG can declare 4096x4096)."""
    if image.format is wire.ImageFormat.PNG:
        header = wire.png_header(image.data)
        size = None if header is None else header[:2]
    else:
        size = wire.jpeg_size(image.data)
    if size is None:
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}.data: expected a {image.format.value.upper()} header")
    if size != camera.size:
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}.data: the {image.format.value} header declares "
                            f"{size[0]}x{size[1]}; expected the camera's "
                            f"{camera.width}x{camera.height}")


def decode_depth(depth: wire.WireDepth, path: str) -> npt.NDArray[np.float32]:
    """(H, W) float32 Z-depth in metres, NaN where the raw value is 0."""
    if depth.format is wire.DepthFormat.MONO16:
        return depth.to_metres()
    raw = cv2.imdecode(np.frombuffer(depth.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.shape != (depth.height, depth.width):
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}.data: expected a {depth.width}x{depth.height} 16-bit PNG "
                            "that decodes")
    metres = (raw * depth.metres_per_unit).astype(np.float32)
    metres[raw == 0] = np.nan
    return metres


def resolve_camera(rt: CameraRegistry, camera_id: str | None, camera: wire.WireCamera | None,
                   path: str) -> Camera:
    """The inline camera, or the registered ``camera_id`` (UNKNOWN_CAMERA if never put)."""
    if camera is not None:
        return to_camera(camera, f"{path}.camera")
    assert camera_id is not None
    found = rt.camera(camera_id)
    if found is None:
        raise ProtocolError(ErrorCode.UNKNOWN_CAMERA,
                            f"{path}.camera_id: camera {camera_id!r} was never put on map "
                            f"{rt.name!r}; known: {sorted(rt.camera_ids())}")
    return found


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
    answer = replace(result, timings=timings, request_id=request.request_id,
                     timestamp=request.timestamp)
    rt.stats.record_relocalize(result.ok, timings["total"])
    return reply_from_result(answer).encode()


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


def status(rt: MapRuntime, payload: bytes) -> bytes:
    """Empty payload -> StatusReply bytes."""
    if payload:
        wire.unpack_message(payload, rt.limits)  # a payload is not expected, but a valid one is OK
    return rt.status().encode()


# -- map copying ------------------------------------------------------------------------------

def keyframe_infos(rt: MapRuntime, *, images: bool) -> list[tuple[int, bytes]]:
    """(keyframe id, KeyframeInfo bytes) of every keyframe, in the order they were added to
    the map (a replica replays them in that order: see bootstrap.Bootstrap); with ``images``, each
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


# -- map building (decoded here, applied by the runtime's writer) -----------------------------

@dataclass(frozen=True, eq=False)
class KeyframeInput:
    """A validated, decoded keyframe put, ready for the engine."""

    kf_id: int
    image: npt.NDArray[np.uint8]
    camera: Camera
    camera_id: str | None
    world_from_cam: Array
    timestamp: float | None
    depth: npt.NDArray[np.float32] | None
    keypoints_px: Array | None
    landmark_ids: npt.NDArray[np.int64] | None
    points_world: Array | None

    def engine_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of the engine's ``add_keyframe`` beyond the positional ones."""
        kw: dict[str, Any] = {"depth": self.depth, "timestamp": self.timestamp}
        if self.keypoints_px is not None:
            kw.update(given_keypoints_px=self.keypoints_px,
                      given_landmark_ids=self.landmark_ids, given_points_world=self.points_world)
        return kw


def decode_keyframe_put(rt: CameraRegistry, kf_id: int, payload: bytes) -> KeyframeInput:
    """Validate a KeyframePut for key id ``kf_id`` and decode its image, depth and features."""
    put = wire.KeyframePut.decode(payload, rt.limits)
    if put.id != kf_id:
        raise ProtocolError(ErrorCode.BAD_VALUE,
                            f"keyframe.id: {put.id} does not match the key's id {kf_id}")
    camera = resolve_camera(rt, put.camera_id, put.camera, "keyframe")
    image = decode_image(put.image, camera, "keyframe.image")
    depth = None if put.depth is None else decode_depth(put.depth, "keyframe.depth")
    kp = ids = pts = None
    if put.features is not None:
        kp, ids, pts = _given_features(put.features, camera)
    return KeyframeInput(kf_id, image, camera, put.camera_id, put.world_from_cam.matrix(),
                         put.timestamp, depth, kp, ids, pts)


def _given_features(features: wire.WireFeatures, camera: Camera
                    ) -> tuple[Array, npt.NDArray[np.int64], Array]:
    n = len(features)
    kp = np.asarray(features.keypoints_px, dtype=np.float64)
    ids = (np.full(n, -1, np.int64) if features.landmark_ids is None
           else np.asarray(features.landmark_ids, dtype=np.int64))
    pts = (np.full((n, 3), np.nan) if features.points_world is None
           else np.asarray(features.points_world, dtype=np.float64))
    if np.any((ids >= 0) & ~np.isfinite(pts).all(axis=1)):
        raise ProtocolError(ErrorCode.BAD_FEATURES,
                            "keyframe.features: every keypoint with a landmark id needs its 3-D "
                            "point in points_world")
    inside = camera.in_image(kp) if n else np.ones(0, bool)
    if not np.all(inside):
        raise ProtocolError(ErrorCode.BAD_FEATURES,
                            f"keyframe.features.keypoints_px: {int((~inside).sum())} keypoint(s) "
                            f"outside the {camera.width}x{camera.height} image")
    return kp, ids, pts


def decode_camera_put(camera_id: str, payload: bytes, limits: wire.Limits) -> Camera:
    """Validate a CameraPut for key id ``camera_id``; the core camera."""
    put = wire.CameraPut.decode(payload, limits)
    if put.id != camera_id:
        raise ProtocolError(ErrorCode.BAD_VALUE,
                            f"camera_put.id: {put.id!r} does not match the key's id "
                            f"{camera_id!r}")
    return to_camera(put.camera, "camera_put.camera")
