"""Messages that build a map: a keyframe put (:class:`KeyframePut`), a keyframe's listing
(:class:`KeyframeInfo`) and a camera put (:class:`CameraPut`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from .checks import (
    ErrorCode,
    Limits,
    ProtocolError,
    _Fields,
    _float,
    _int,
)
from .geometry import WireCamera, WirePose
from .images import WireDepth, WireFeatures, WireImage
from .keys import _check_kf_id, check_name
from .message_base import (
    Message,
    _camera_choice,
    _opt_list,
    _opt_wire,
    _pose_covariance,
)


@dataclass(frozen=True)
class KeyframePut(Message):
    """Put on ``<prefix>/<map>/keyframes/<id>``: add or replace keyframe ``id``."""

    NAME: ClassVar[str] = "keyframe"
    id: int
    image: WireImage
    world_from_cam: WirePose
    camera_id: str | None = None
    camera: WireCamera | None = None
    timestamp: float | None = None
    features: WireFeatures | None = None
    depth: WireDepth | None = None
    #: 6x6 row-major covariance of ``world_from_cam`` (36 floats; twist (rho, omega), right
    #: perturbation, metres and radians); None: the map's default applies.
    pose_covariance: tuple[float, ...] | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "image": self.image.to_wire(), "camera_id": self.camera_id,
                "camera": _opt_wire(self.camera), "world_from_cam": self.world_from_cam.to_wire(),
                "timestamp": self.timestamp, "features": _opt_wire(self.features),
                "depth": _opt_wire(self.depth),
                "pose_covariance": _opt_list(self.pose_covariance)}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> KeyframePut:
        f = _Fields(value, path)
        f.seen.add("v")
        kf_id = f.req("id", _check_kf_id)
        image = f.req("image", lambda v, p: WireImage.from_wire(v, p, limits))
        camera_id, camera = _camera_choice(f, path, image)
        pose = f.req("world_from_cam", WirePose.from_wire)
        timestamp = f.opt("timestamp", _float)
        features = f.opt("features", lambda v, p: WireFeatures.from_wire(v, p, limits))
        depth = f.opt("depth", lambda v, p: WireDepth.from_wire(v, p, limits))
        pose_covariance = f.opt("pose_covariance", _pose_covariance)
        f.done()
        if depth is not None and (depth.width, depth.height) != (image.width, image.height):
            raise ProtocolError(ErrorCode.BAD_IMAGE,
                                f"{path}.depth: size {depth.width}x{depth.height} does not "
                                f"match the image's {image.width}x{image.height}")
        return cls(kf_id, image, pose, camera_id, camera, timestamp, features, depth,
                   pose_covariance)


@dataclass(frozen=True)
class KeyframeInfo(Message):
    """A reply to a get on ``<prefix>/<map>/keyframes/**`` (one per stored keyframe); the
    image is included only when the selector has the parameter ``image=true``."""

    NAME: ClassVar[str] = "keyframe_info"
    id: int
    camera: WireCamera
    world_from_cam: WirePose
    camera_id: str | None = None
    timestamp: float | None = None
    num_landmarks: int = 0
    image: WireImage | None = None
    #: As in :class:`KeyframePut`: the covariance the keyframe was put with (None: none was,
    #: the map's default applies).
    pose_covariance: tuple[float, ...] | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "camera": self.camera.to_wire(), "camera_id": self.camera_id,
                "world_from_cam": self.world_from_cam.to_wire(), "timestamp": self.timestamp,
                "num_landmarks": self.num_landmarks, "image": _opt_wire(self.image),
                "pose_covariance": _opt_list(self.pose_covariance)}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> KeyframeInfo:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(
            id=f.req("id", _check_kf_id),
            camera=f.req("camera", WireCamera.from_wire),
            world_from_cam=f.req("world_from_cam", WirePose.from_wire),
            camera_id=f.opt("camera_id", lambda v, p: check_name(v, p)),
            timestamp=f.opt("timestamp", _float),
            num_landmarks=f.opt("num_landmarks", lambda v, p: _int(v, p, lo=0), 0),
            image=f.opt("image", lambda v, p: WireImage.from_wire(v, p, limits)),
            pose_covariance=f.opt("pose_covariance", _pose_covariance))
        f.done()
        return out


@dataclass(frozen=True)
class CameraPut(Message):
    """Put on ``<prefix>/<map>/cameras/<id>`` (also a reply to a get on ``cameras/**``)."""

    NAME: ClassVar[str] = "camera_put"
    id: str
    camera: WireCamera

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "camera": self.camera.to_wire()}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> CameraPut:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.req("id", lambda v, p: check_name(v, p)), f.req("camera", WireCamera.from_wire))
        f.done()
        return out
