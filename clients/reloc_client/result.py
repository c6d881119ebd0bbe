"""The one relocalization result, shared by the service and the client, and its wire edge.

A relocalizer answers a :class:`RelocResult`; the service sends it as a
:class:`~reloc_client.protocol.RelocalizeReply` (:func:`reply_from_result`) and the client
reads it back (:func:`result_from_reply`). These two functions are the only places where a
result and a reply meet, so a field added to both needs one change here. Imports numpy and
``reloc_client.protocol`` only (no zenoh, no OpenCV), so the service's core can use it.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from . import protocol as wire

Array = npt.NDArray[np.float64]


class RelocStatus(enum.Enum):
    """Outcome of a relocalization query that was answered (``busy`` is not an outcome: the
    client raises ServiceBusy for it)."""

    OK = "ok"
    NOT_RELOCALIZED = "not_relocalized"


# Mutable (not frozen) because the engine stamps the map version and its own timings on the
# result a relocalizer returned; eq=False because numpy fields have no single truth value.
@dataclass(eq=False)
class RelocResult:
    """What a relocalizer answers. ``world_from_cam`` (4, 4) float64 is None unless ``status``
    is OK; ``reason`` says why not.

    ``covariance`` is (6, 6) (twist (rho, omega), right perturbation, metres and radians) or
    None; ``timings`` are seconds per stage (decode, features, place, match, solve, verify,
    ...); ``hypotheses`` are further verified poses, best first, when more than one was asked
    for. ``request_id`` and ``timestamp`` echo the request; ``round_trip_s`` is measured by
    the client (None in the service).
    """

    status: RelocStatus
    method: str
    world_from_cam: Array | None = None
    reason: str = ""
    confidence: float = 0.0
    inliers: int = 0
    num_matches: int = 0
    reprojection_rms_px: float | None = None
    covariance: Array | None = None
    matched_keyframe_ids: list[int] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    map_version: int = 0
    hypotheses: list[RelocResult] = field(default_factory=list)
    request_id: str | None = None
    timestamp: float | None = None
    round_trip_s: float | None = None

    @property
    def ok(self) -> bool:
        return self.status is RelocStatus.OK

    @classmethod
    def failure(cls, method: str, reason: str, **kw: Any) -> RelocResult:
        """NOT_RELOCALIZED by ``method`` because of ``reason`` (other fields as keywords)."""
        return cls(status=RelocStatus.NOT_RELOCALIZED, method=method, reason=reason, **kw)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict; the pose as ``world_from_cam_tum`` (tx ty tz qx qy qz qw) and as a
        4x4 row-major ``world_from_cam``."""
        d: dict[str, Any] = {"status": self.status.value, "method": self.method,
                             "reason": self.reason}
        if self.world_from_cam is not None:
            p = wire.WirePose.from_matrix(self.world_from_cam)
            d["world_from_cam_tum"] = [*p.t, *p.q]
            d["world_from_cam"] = np.asarray(self.world_from_cam).tolist()
        d.update(confidence=self.confidence, inliers=self.inliers, num_matches=self.num_matches,
                 reprojection_rms_px=self.reprojection_rms_px,
                 covariance=None if self.covariance is None else self.covariance.tolist(),
                 matched_keyframe_ids=self.matched_keyframe_ids, map_version=self.map_version,
                 timings=self.timings, round_trip_s=self.round_trip_s)
        if self.request_id is not None:
            d["request_id"] = self.request_id
        if self.hypotheses:
            d["hypotheses"] = [h.to_dict() for h in self.hypotheses]
        return d


# -- the wire edge ----------------------------------------------------------------------------

def reply_from_result(result: RelocResult) -> wire.RelocalizeReply:
    """The wire reply for ``result``.

    A relocalizer's numbers are not trusted to be wire-valid: a pose is sent only when OK,
    the confidence is clipped to [0, 1], and non-finite or negative optional numbers
    (RMS, covariance, timings, keyframe ids) are left out, since the strict decoder on the
    other side refuses them. Only verified (OK) hypotheses travel.
    """
    pose = result.world_from_cam if result.ok else None
    ok = pose is not None
    return wire.RelocalizeReply(
        status=wire.ReplyStatus.OK if ok else wire.ReplyStatus.NOT_RELOCALIZED,
        method=result.method,
        world_from_cam=None if pose is None else wire.WirePose.from_matrix(pose),
        covariance=_covariance_to_wire(result.covariance) if ok else None,
        confidence=float(np.clip(result.confidence, 0.0, 1.0)) if ok else 0.0,
        inliers=max(int(result.inliers), 0), num_matches=max(int(result.num_matches), 0),
        reprojection_rms_px=_finite_or_none(result.reprojection_rms_px),
        matched_keyframe_ids=_keyframe_ids_to_wire(result.matched_keyframe_ids),
        map_version=max(int(result.map_version), 0),
        timings={k: float(v) for k, v in result.timings.items() if np.isfinite(v) and v >= 0},
        reason="" if ok else (result.reason or "not relocalized"),
        hypotheses=tuple(_hypothesis_to_wire(h) for h in result.hypotheses if h.ok),
        request_id=result.request_id, timestamp=result.timestamp)


def result_from_reply(reply: wire.RelocalizeReply, *,
                      round_trip_s: float | None = None) -> RelocResult:
    """The result a decoded ``reply`` carries; ValueError for a ``busy`` reply, which
    carries none (the client turns it into ServiceBusy before calling this)."""
    if reply.status is wire.ReplyStatus.BUSY:
        raise ValueError("expected an 'ok' or 'not_relocalized' reply, got 'busy' (a busy "
                         "reply carries no result)")
    return RelocResult(
        status=RelocStatus(reply.status.value), method=reply.method,
        world_from_cam=None if reply.world_from_cam is None else reply.world_from_cam.matrix(),
        reason=reply.reason, confidence=reply.confidence, inliers=reply.inliers,
        num_matches=reply.num_matches, reprojection_rms_px=reply.reprojection_rms_px,
        covariance=_covariance_from_wire(reply.covariance),
        matched_keyframe_ids=list(reply.matched_keyframe_ids), timings=dict(reply.timings),
        map_version=reply.map_version,
        hypotheses=[_hypothesis_from_wire(h, reply.map_version) for h in reply.hypotheses],
        request_id=reply.request_id, timestamp=reply.timestamp, round_trip_s=round_trip_s)


def _hypothesis_to_wire(h: RelocResult) -> wire.Hypothesis:
    assert h.world_from_cam is not None, "an OK hypothesis carries a pose"
    return wire.Hypothesis(
        world_from_cam=wire.WirePose.from_matrix(h.world_from_cam), method=h.method,
        confidence=float(np.clip(h.confidence, 0.0, 1.0)), inliers=max(int(h.inliers), 0),
        num_matches=max(int(h.num_matches), 0),
        reprojection_rms_px=_finite_or_none(h.reprojection_rms_px),
        covariance=_covariance_to_wire(h.covariance),
        matched_keyframe_ids=_keyframe_ids_to_wire(h.matched_keyframe_ids))


def _hypothesis_from_wire(h: wire.Hypothesis, map_version: int) -> RelocResult:
    # A hypothesis is a verified pose of the same query and map: OK, the reply's map version.
    return RelocResult(
        status=RelocStatus.OK, method=h.method, world_from_cam=h.world_from_cam.matrix(),
        confidence=h.confidence, inliers=h.inliers, num_matches=h.num_matches,
        reprojection_rms_px=h.reprojection_rms_px, covariance=_covariance_from_wire(h.covariance),
        matched_keyframe_ids=list(h.matched_keyframe_ids), map_version=map_version)


def _covariance_to_wire(covariance: Array | None) -> tuple[float, ...] | None:
    if covariance is None:
        return None
    c = np.asarray(covariance, dtype=np.float64)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)):
        return None
    return tuple(float(v) for v in c.ravel())


def _covariance_from_wire(values: Sequence[float] | None) -> Array | None:
    return None if values is None else np.array(values, dtype=np.float64).reshape(6, 6)


def _keyframe_ids_to_wire(ids: Sequence[int]) -> tuple[int, ...]:
    # Negative ids are "no keyframe" placeholders of some relocalizers, not wire ids.
    return tuple(int(k) for k in ids if k >= 0)


def _finite_or_none(x: float | None) -> float | None:
    if x is None or not np.isfinite(x) or x < 0:
        return None
    return float(x)


__all__ = ["RelocResult", "RelocStatus", "reply_from_result", "result_from_reply"]
