"""``reloc_client.result``: the one result type of service and client, and its wire edge."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import reloc_client
from reloc_client import protocol as P
from reloc_client.result import (
    RelocResult,
    RelocStatus,
    reply_from_result,
    result_from_reply,
)

from reloc_service.algorithms import relocalizers
from reloc_service.algorithms.relocalizers import base
from reloc_service.core.geometry import look_at, se3_exp

ROOT = Path(__file__).resolve().parents[1]


def test_client_and_service_share_one_result_class():
    from reloc_client import client

    assert base.RelocResult is relocalizers.RelocResult is RelocResult
    assert client.RelocResult is reloc_client.RelocResult is RelocResult
    assert base.RelocStatus is client.RelocStatus is reloc_client.RelocStatus is RelocStatus


def test_the_result_loads_without_zenoh():
    code = ("import sys, reloc_client; reloc_client.RelocResult; reloc_client.result_from_reply; "
            "assert 'zenoh' not in sys.modules, 'zenoh was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return look_at(rng.normal(size=3), (0.0, 3.0, 1.0)) @ se3_exp(rng.normal(size=6) * 0.1)


def _covariance(seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(6, 6)) * 1e-2
    return a @ a.T


def _ok(seed: int, **kw) -> RelocResult:
    return RelocResult(RelocStatus.OK, "bow+p3p", _pose(seed), confidence=0.8, inliers=120,
                       num_matches=300, reprojection_rms_px=0.7,
                       matched_keyframe_ids=[4, 2], **kw)


RESULTS = {
    "ok": _ok(0, timings={"place": 0.002, "solve": 0.0105}, map_version=7),
    "ok_with_covariance_and_hypotheses": _ok(
        1, covariance=_covariance(1), map_version=3, request_id="q-17", timestamp=12.5,
        hypotheses=[_ok(2, covariance=_covariance(2), map_version=3),
                    _ok(3, map_version=3)]),
    "not_relocalized": RelocResult.failure("sbi+esm", "too few inliers (4 < 10)", inliers=4,
                                           num_matches=31, matched_keyframe_ids=[9],
                                           map_version=2, timings={"place": 0.001}),
}


def _assert_same(a: RelocResult, b: RelocResult) -> None:
    """Every field equal; arrays to float precision (a pose travels as t + quaternion)."""
    for name in ("status", "method", "reason", "confidence", "inliers", "num_matches",
                 "reprojection_rms_px", "matched_keyframe_ids", "timings", "map_version",
                 "request_id", "timestamp"):
        assert getattr(a, name) == getattr(b, name), name
    for name in ("world_from_cam", "covariance"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert y.shape == x.shape and y.dtype == np.float64
            np.testing.assert_allclose(y, x, atol=1e-12, err_msg=name)
    assert len(a.hypotheses) == len(b.hypotheses)
    for h, g in zip(a.hypotheses, b.hypotheses, strict=True):
        _assert_same(h, g)


@pytest.mark.parametrize("name", sorted(RESULTS))
def test_result_round_trips_through_the_wire(name):
    result = RESULTS[name]
    payload = reply_from_result(result).encode()
    back = result_from_reply(P.RelocalizeReply.decode(payload), round_trip_s=0.25)
    _assert_same(result, back)
    assert back.round_trip_s == 0.25 and result.round_trip_s is None


def test_reply_leaves_out_what_the_wire_refuses():
    result = RelocResult(RelocStatus.OK, "sbi+p3p", _pose(4), confidence=1.7, inliers=-1,
                         reprojection_rms_px=float("nan"), matched_keyframe_ids=[3, -1],
                         covariance=np.full((6, 6), np.inf),
                         timings={"solve": 0.01, "bad": float("nan"), "neg": -1.0},
                         hypotheses=[RelocResult.failure("sbi+p3p", "weak")])
    reply = P.RelocalizeReply.decode(reply_from_result(result).encode())
    assert reply.confidence == 1.0 and reply.inliers == 0
    assert reply.reprojection_rms_px is None and reply.covariance is None
    assert reply.matched_keyframe_ids == (3,) and dict(reply.timings) == {"solve": 0.01}
    assert reply.hypotheses == ()  # only verified hypotheses travel


def test_a_refusal_travels_without_a_pose_and_with_a_reason():
    # A NOT_RELOCALIZED result that still holds the rejected estimate must not send it.
    refused = RelocResult(RelocStatus.NOT_RELOCALIZED, "sbi+p3p", _pose(5), confidence=0.4,
                          covariance=_covariance(5))
    reply = P.RelocalizeReply.decode(reply_from_result(refused).encode())
    assert reply.status is P.ReplyStatus.NOT_RELOCALIZED and reply.world_from_cam is None
    assert reply.covariance is None and reply.confidence == 0.0
    assert reply.reason == "not relocalized"


def test_a_busy_reply_carries_no_result():
    with pytest.raises(ValueError, match="expected an 'ok' or 'not_relocalized' reply, got 'busy'"):
        result_from_reply(P.RelocalizeReply(P.ReplyStatus.BUSY, reason="queue full"))


def test_to_dict_is_json_ready():
    import json

    d = RESULTS["ok_with_covariance_and_hypotheses"].to_dict()
    assert json.loads(json.dumps(d)) == d
    assert d["status"] == "ok" and len(d["world_from_cam_tum"]) == 7 and d["request_id"] == "q-17"
    assert len(d["hypotheses"]) == 2 and np.array(d["covariance"]).shape == (6, 6)
