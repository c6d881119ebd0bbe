"""Wire <-> core conversions of the service, and the error mapping.

Decoding is strict (``reloc_client.protocol`` validates the message; here images, depths,
cameras and given features become core types, checked against the map's cameras), so the
handlers, the map runtime (journal replay) and the replica bootstrap share one definition of
what a valid put is. :func:`error_of` maps any exception to the protocol's error code.
Nothing here knows about Zenoh or about a map runtime: a map is seen only through
:class:`CameraRegistry`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt
from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, ProtocolError

from ..core.cameras import Camera, camera_from_dict
from ..core.errors import CameraError, ConfigError, GeometryError, MapError, NotTrainedError, StorageError
from ..core.frame import EncodedImage
from ..core.methods import parse_method

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


def keyframe_image(image: wire.WireImage, camera: Camera, path: str
                   ) -> npt.NDArray[np.uint8] | EncodedImage:
    """A keyframe's image as the map keeps it: the bytes sent when they are a JPEG or an
    8-bit grey PNG (checked to decode like :func:`decode_image`: a saved map stores them
    instead of re-encoding the pixels, a JPEG at a third of a PNG's size), else the pixels."""
    pixels = decode_image(image, camera, path)
    png = wire.png_header(image.data) if image.format is wire.ImageFormat.PNG else None
    if image.format is wire.ImageFormat.JPEG or (png is not None and png[2:] == (8, 0)):
        encoded = EncodedImage(bytes(image.data), pixels.shape)
        encoded.remember(pixels)     # the map extracts features from these: no second decode
        return encoded
    return pixels


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


def served_method(map_name: str, methods: tuple[str, ...], default_method: str,
                  method: str | None) -> str:
    """``method`` (default: ``default_method``) in its canonical form if that is one of
    ``methods``; UNKNOWN_METHOD naming the served ones otherwise (a method that does not
    parse is served by no name)."""
    if method is None:
        return default_method
    try:
        method = str(parse_method(method))
    except ConfigError:
        method = method.strip()
    if method not in methods:
        raise ProtocolError(ErrorCode.UNKNOWN_METHOD,
                            f"method {method!r} is not served on map {map_name!r}; "
                            f"served: {list(methods)}")
    return method


# -- map building (decoded here, applied by the runtime's writer) -----------------------------

@dataclass(frozen=True, eq=False)
class KeyframeInput:
    """A validated, decoded keyframe put, ready for the engine."""

    kf_id: int
    #: the client's JPEG or grey PNG as sent (checked to decode; the map keeps and saves it
    #: as it is), or the pixels (raw MONO8, or a PNG in another colour type or depth)
    image: npt.NDArray[np.uint8] | EncodedImage
    camera: Camera
    camera_id: str | None
    world_from_cam: Array
    timestamp: float | None
    depth: npt.NDArray[np.float32] | None
    keypoints_px: Array | None
    landmark_ids: npt.NDArray[np.int64] | None
    points_world: Array | None
    #: (6, 6) covariance of ``world_from_cam`` as put; None: the map's default applies
    pose_covariance: Array | None = None

    def engine_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of the engine's ``add_keyframe`` beyond the positional ones."""
        kw: dict[str, Any] = {"depth": self.depth, "timestamp": self.timestamp,
                              "pose_covariance": self.pose_covariance}
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
    image = keyframe_image(put.image, camera, "keyframe.image")
    depth = None if put.depth is None else decode_depth(put.depth, "keyframe.depth")
    kp = ids = pts = None
    if put.features is not None:
        kp, ids, pts = _given_features(put.features, camera)
    return KeyframeInput(kf_id, image, camera, put.camera_id, put.world_from_cam.matrix(),
                         put.timestamp, depth, kp, ids, pts, pose_covariance_of(put))


def pose_covariance_of(message: wire.KeyframePut | wire.KeyframeInfo) -> Array | None:
    """The (6, 6) pose covariance a keyframe message carries (validated by its decoder), or
    None."""
    if message.pose_covariance is None:
        return None
    return np.reshape(np.asarray(message.pose_covariance, np.float64), (6, 6))


def pose_covariance_to_wire(covariance: Array | None) -> tuple[float, ...] | None:
    """A keyframe's (6, 6) pose covariance as the 36 row-major floats of the wire, or None."""
    return None if covariance is None else tuple(float(v) for v in np.ravel(covariance))


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


class WithLimits:
    """``registry`` seen under other ``limits`` (the journal replay decodes with none: what
    was accepted once is accepted again)."""

    def __init__(self, registry: CameraRegistry, limits: wire.Limits) -> None:
        self._registry = registry
        self.limits = limits
        self.name = registry.name

    def camera(self, camera_id: str) -> Camera | None:
        return self._registry.camera(camera_id)

    def camera_ids(self) -> list[str]:
        return self._registry.camera_ids()
