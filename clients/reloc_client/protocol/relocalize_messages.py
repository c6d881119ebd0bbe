"""The relocalize query and its reply: the query's optional :class:`Prior`, the
:class:`RelocalizeRequest`, each :class:`Hypothesis` considered and the
:class:`RelocalizeReply`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from .checks import (
    _SHORT,
    DEFAULT_LIMITS,
    ErrorCode,
    Limits,
    ProtocolError,
    _Fields,
    _float,
    _int,
    _list,
    _str,
)
from .geometry import WireCamera, WirePose
from .images import WireImage
from .message_base import (
    Message,
    ReplyStatus,
    _camera_choice,
    _covariance,
    _drop_none,
    _enum,
    _kf_ids,
    _method,
    _opt_wire,
    _pose_covariance,
    _timings,
)


@dataclass(frozen=True)
class Prior:
    """A ``world_from_cam`` the caller believes in (a VIO's, say), with at least one of:

    - ``radius_m``: candidates of the place finders are keyframes whose centre is within that
      many metres of its centre (as before the covariance existed);
    - ``covariance``: 36 numbers, row-major, the 6x6 covariance of the prior (twist (rho,
      omega), right perturbation ``world_from_cam @ exp(xi)``, metres and radians, as every
      pose covariance of the protocol): the service first tracks, matching the landmarks
      the prior predicts visible in windows this covariance sets, and only where that does
      not verify runs the full method (restricted by ``radius_m`` when also given).
    """

    world_from_cam: WirePose
    radius_m: float | None = None
    covariance: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.radius_m is None and self.covariance is None:
            raise ProtocolError(ErrorCode.MISSING_FIELD,
                                "prior: expected 'radius_m' (metres), 'covariance' (36 numbers, "
                                "a 6x6 pose covariance) or both")
        if self.covariance is not None:
            _pose_covariance(list(self.covariance), "prior.covariance")

    def to_wire(self) -> dict[str, Any]:
        out: dict[str, Any] = {"world_from_cam": self.world_from_cam.to_wire()}
        if self.radius_m is not None:
            out["radius_m"] = self.radius_m
        if self.covariance is not None:
            out["covariance"] = list(self.covariance)
        return out

    @classmethod
    def from_wire(cls, value: Any, path: str) -> Prior:
        f = _Fields(value, path)
        pose = f.req("world_from_cam", WirePose.from_wire)
        radius = f.opt("radius_m", lambda v, p: _float(v, p, positive=True))
        covariance = f.opt("covariance", _pose_covariance)
        f.done()
        if radius is None and covariance is None:
            raise ProtocolError(ErrorCode.MISSING_FIELD,
                                f"{path}: expected 'radius_m' (metres), 'covariance' (36 "
                                f"numbers, a 6x6 pose covariance) or both")
        return cls(pose, radius, covariance)


@dataclass(frozen=True)
class RelocalizeRequest(Message):
    """Query on ``<prefix>/<map>/relocalize``: where was this image taken?"""

    NAME: ClassVar[str] = "relocalize"
    image: WireImage
    camera_id: str | None = None
    camera: WireCamera | None = None
    method: str | None = None
    prior: Prior | None = None
    hypotheses: int = 1
    request_id: str | None = None
    timestamp: float | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"image": self.image.to_wire(), "camera_id": self.camera_id,
                "camera": _opt_wire(self.camera), "method": self.method,
                "prior": _opt_wire(self.prior),
                "hypotheses": None if self.hypotheses == 1 else self.hypotheses,
                "request_id": self.request_id, "timestamp": self.timestamp}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> RelocalizeRequest:
        f = _Fields(value, path)
        f.seen.add("v")
        image = f.req("image", lambda v, p: WireImage.from_wire(v, p, limits))
        camera_id, camera = _camera_choice(f, path, image)
        out = cls(
            image=image, camera_id=camera_id, camera=camera,
            method=f.opt("method", _method),
            prior=f.opt("prior", Prior.from_wire),
            hypotheses=f.opt("hypotheses", lambda v, p: _int(v, p, lo=1, hi=limits.max_hypotheses),
                             1),
            request_id=f.opt("request_id", lambda v, p: _str(v, p, _SHORT)),
            timestamp=f.opt("timestamp", _float))
        f.done()
        return out


@dataclass(frozen=True)
class Hypothesis:
    """One further verified pose of a relocalize reply (fields as in the reply)."""

    world_from_cam: WirePose
    method: str = ""
    confidence: float = 0.0
    inliers: int = 0
    num_matches: int = 0
    reprojection_rms_px: float | None = None
    covariance: tuple[float, ...] | None = None
    matched_keyframe_ids: tuple[int, ...] = ()

    def to_wire(self) -> dict[str, Any]:
        return _drop_none({
            "world_from_cam": self.world_from_cam.to_wire(), "method": self.method,
            "confidence": self.confidence, "inliers": self.inliers,
            "num_matches": self.num_matches, "reprojection_rms_px": self.reprojection_rms_px,
            "covariance": None if self.covariance is None else list(self.covariance),
            "matched_keyframe_ids": list(self.matched_keyframe_ids)})

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits = DEFAULT_LIMITS) -> Hypothesis:
        f = _Fields(value, path)
        out = cls(
            world_from_cam=f.req("world_from_cam", WirePose.from_wire),
            method=f.opt("method", lambda v, p: _str(v, p, limits), ""),
            confidence=f.opt("confidence", lambda v, p: _float(v, p, unit=True), 0.0),
            inliers=f.opt("inliers", lambda v, p: _int(v, p, lo=0), 0),
            num_matches=f.opt("num_matches", lambda v, p: _int(v, p, lo=0), 0),
            reprojection_rms_px=f.opt("reprojection_rms_px",
                                      lambda v, p: _float(v, p, non_negative=True)),
            covariance=f.opt("covariance", _covariance),
            matched_keyframe_ids=f.opt("matched_keyframe_ids",
                                       lambda v, p: _kf_ids(v, p, limits), ()))
        f.done()
        return out


@dataclass(frozen=True)
class RelocalizeReply(Message):
    """Reply to a relocalize query. ``world_from_cam`` is set iff ``status`` is ``ok``;
    ``covariance`` is 6x6 row-major (twist (rho, omega), right perturbation, m and rad)."""

    NAME: ClassVar[str] = "relocalize_reply"
    status: ReplyStatus
    method: str = ""
    world_from_cam: WirePose | None = None
    covariance: tuple[float, ...] | None = None
    confidence: float = 0.0
    inliers: int = 0
    num_matches: int = 0
    reprojection_rms_px: float | None = None
    matched_keyframe_ids: tuple[int, ...] = ()
    map_version: int = 0
    timings: Mapping[str, float] = field(default_factory=dict)
    reason: str = ""
    hypotheses: tuple[Hypothesis, ...] = ()
    request_id: str | None = None
    timestamp: float | None = None

    def to_wire(self) -> dict[str, Any]:
        return {
            "status": ReplyStatus(self.status).value, "method": self.method,
            "world_from_cam": _opt_wire(self.world_from_cam),
            "covariance": None if self.covariance is None else list(self.covariance),
            "confidence": self.confidence, "inliers": self.inliers,
            "num_matches": self.num_matches, "reprojection_rms_px": self.reprojection_rms_px,
            "matched_keyframe_ids": list(self.matched_keyframe_ids),
            "map_version": self.map_version, "timings": dict(self.timings),
            "reason": self.reason, "hypotheses": [h.to_wire() for h in self.hypotheses],
            "request_id": self.request_id, "timestamp": self.timestamp}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> RelocalizeReply:
        f = _Fields(value, path)
        f.seen.add("v")
        status = f.req("status", lambda v, p: _enum(ReplyStatus, v, p))
        out = cls(
            status=status,
            method=f.opt("method", lambda v, p: _str(v, p, limits), ""),
            world_from_cam=f.opt("world_from_cam", WirePose.from_wire),
            covariance=f.opt("covariance", _covariance),
            confidence=f.opt("confidence", lambda v, p: _float(v, p, unit=True), 0.0),
            inliers=f.opt("inliers", lambda v, p: _int(v, p, lo=0), 0),
            num_matches=f.opt("num_matches", lambda v, p: _int(v, p, lo=0), 0),
            reprojection_rms_px=f.opt("reprojection_rms_px",
                                      lambda v, p: _float(v, p, non_negative=True)),
            matched_keyframe_ids=f.opt("matched_keyframe_ids",
                                       lambda v, p: _kf_ids(v, p, limits), ()),
            map_version=f.opt("map_version", lambda v, p: _int(v, p, lo=0), 0),
            timings=f.opt("timings", lambda v, p: _timings(v, p, limits), {}),
            reason=f.opt("reason", lambda v, p: _str(v, p, limits), ""),
            hypotheses=f.opt("hypotheses", lambda v, p: _list(
                v, p, limits, lambda h, q: Hypothesis.from_wire(h, q, limits)), ()),
            request_id=f.opt("request_id", lambda v, p: _str(v, p, limits)),
            timestamp=f.opt("timestamp", _float))
        f.done()
        if (status is ReplyStatus.OK) != (out.world_from_cam is not None):
            raise ProtocolError(ErrorCode.BAD_VALUE,
                                f"{path}.world_from_cam: expected a pose exactly when status is "
                                f"'ok', status is {status.value!r}")
        return out
