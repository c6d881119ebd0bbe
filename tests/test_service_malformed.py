"""Every malformed input class over real Zenoh on loopback: each malformed relocalize request
gets its error code and the service answers the next query; each malformed keyframe put is
rejected with an event and stores nothing."""

from __future__ import annotations

import cv2
import msgpack
import numpy as np
import pytest
from reloc_client import protocol as wire
from service_api_support import MAP, served_api
from service_support import BLOCK, raw_session


@pytest.fixture(scope="module")
def served(synthetic_scene, tmp_path_factory):
    yield from served_api(synthetic_scene, tmp_path_factory)


def _request(scene, **changes):
    img = scene.query_images[0]
    request = {"v": 1, "camera_id": "cam0",
               "image": {"format": "mono8", "width": img.shape[1], "height": img.shape[0],
                         "data": img.tobytes()}}
    request.update(changes)
    return msgpack.packb({k: v for k, v in request.items() if v is not None}, use_bin_type=True)


def _image(fmt, data, width=320, height=240):
    return {"format": fmt, "width": width, "height": height, "data": data}


def _corrupt_png():
    ok, png = cv2.imencode(".png", np.zeros((240, 320), np.uint8))
    data = bytearray(png.tobytes())
    data[60:] = b"\x00" * (len(data) - 60)         # header intact, pixel data destroyed
    return bytes(data)


def _corrupt_jpeg():
    ok, jpg = cv2.imencode(".jpg", np.full((240, 320), 128, np.uint8))
    data = jpg.tobytes()
    return data[: len(data) // 3]                  # header intact, scan cut short


NAN_POSE = {"t": [float("nan"), 0.0, 0.0], "q": [0.0, 0.0, 0.0, 1.0]}
UNIT_POSE = {"t": [0.0, 0.0, 0.0], "q": [0.0, 0.0, 0.0, 1.0]}

MALFORMED = {
    "not msgpack": (lambda s: b"\xc1\xc1\xc1", "BAD_MSGPACK"),
    "trailing bytes": (lambda s: _request(s) + b"\x00", "BAD_MSGPACK"),
    "not a map": (lambda s: msgpack.packb([1, 2, 3]), "NOT_A_MAP"),
    "unknown version": (lambda s: _request(s, v=2), "UNSUPPORTED_VERSION"),
    "no version": (lambda s: msgpack.packb({"image": 1}), "MISSING_FIELD"),
    "missing image": (lambda s: _request(s, image=None), "MISSING_FIELD"),
    "unknown field": (lambda s: _request(s, colour="red"), "UNKNOWN_FIELD"),
    "wrong type": (lambda s: _request(s, hypotheses="two"), "WRONG_TYPE"),
    "wrong type image": (lambda s: _request(s, image="x.png"), "WRONG_TYPE"),
    "out of range": (lambda s: _request(s, hypotheses=0), "BAD_VALUE"),
    "no camera": (lambda s: _request(s, camera_id=None), "MISSING_FIELD"),
    "unknown camera": (lambda s: _request(s, camera_id="nope"), "UNKNOWN_CAMERA"),
    "bad camera": (lambda s: _request(s, camera_id=None, camera={
        "model": "pinhole", "width": 320, "height": 240, "fx": -1.0, "fy": 250.0,
        "cx": 160.0, "cy": 120.0}), "BAD_CAMERA"),
    "corrupt png": (lambda s: _request(s, image=_image("png", _corrupt_png())), "BAD_IMAGE"),
    "corrupt jpeg": (lambda s: _request(s, image=_image("jpeg", _corrupt_jpeg())),
                     "BAD_IMAGE"),
    "not an image": (lambda s: _request(s, image=_image("png", b"GIF89a" + b"\0" * 40)),
                     "BAD_IMAGE"),
    "raw size mismatch": (lambda s: _request(s, image=_image("mono8", b"\0" * 100)),
                          "BAD_IMAGE"),
    "size not the camera's": (lambda s: _request(s, image=_image("mono8", b"\0" * 100, 10, 10)),
                              "BAD_IMAGE"),
    "too many pixels": (lambda s: _request(s, image=_image("mono8", b"\0", 5000, 5000)),
                        "IMAGE_TOO_LARGE"),
    "oversized payload": (lambda s: _request(s, request_id=None, image=_image(
        "mono8", b"\0" * 2_100_000, 1500, 1400)), "PAYLOAD_TOO_LARGE"),
    "nan prior": (lambda s: _request(s, prior={"world_from_cam": NAN_POSE, "radius_m": 1.0}),
                  "BAD_POSE"),
    "non-unit quaternion": (lambda s: _request(s, prior={
        "world_from_cam": {"t": [0, 0, 0], "q": [0, 0, 0, 2.0]}, "radius_m": 1.0}), "BAD_POSE"),
    "negative radius": (lambda s: _request(s, prior={"world_from_cam": UNIT_POSE,
                                                     "radius_m": -1.0}), "BAD_VALUE"),
    "prior covariance not positive semi-definite": (lambda s: _request(s, prior={
        "world_from_cam": UNIT_POSE, "covariance": [-1.0 if i == 0 else 0.0
                                                    for i in range(36)]}), "BAD_VALUE"),
    "prior with neither radius nor covariance": (lambda s: _request(s, prior={
        "world_from_cam": UNIT_POSE}), "MISSING_FIELD"),
    "unknown method": (lambda s: _request(s, method="ferns"), "UNKNOWN_METHOD"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_relocalize_requests_get_their_error_code(served, synthetic_scene, case):
    _, port, client, _ = served
    build, code = MALFORMED[case]
    with raw_session(port) as session:
        replies = list(session.get("reloc/lab/relocalize", payload=build(synthetic_scene),
                                   timeout=30))
    assert len(replies) == 1 and replies[0].err is not None, case
    error = wire.ErrorReply.decode(replies[0].err.payload.to_bytes())
    assert error.code.value == code, error.message
    assert error.message
    assert client.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok


def _keyframe_put(scene, kf_id=90, **changes):
    img = scene.keyframe_images[0]
    put = {"v": 1, "id": kf_id, "camera_id": "cam0",
           "image": _image("mono8", img.tobytes()),
           "world_from_cam": {"t": [0.0, 0.3, 1.2], "q": [0.0, 0.0, 0.0, 1.0]}}
    put.update(changes)
    return msgpack.packb({k: v for k, v in put.items() if v is not None}, use_bin_type=True)


BAD_PUTS = {
    "nan pose": (lambda s: _keyframe_put(s, world_from_cam=NAN_POSE), "BAD_POSE"),
    "unknown camera": (lambda s: _keyframe_put(s, camera_id="nope"), "UNKNOWN_CAMERA"),
    "corrupt jpeg": (lambda s: _keyframe_put(s, image=_image("jpeg", _corrupt_jpeg())),
                     "BAD_IMAGE"),
    "id differs from key": (lambda s: _keyframe_put(s, kf_id=91), "BAD_VALUE"),
    "bad features": (lambda s: _keyframe_put(s, features={
        "keypoints_px": np.zeros((4, 2), "<f4").tobytes(),
        "landmark_ids": np.zeros(3, "<i8").tobytes()}), "BAD_FEATURES"),
    "landmark without point": (lambda s: _keyframe_put(s, features={
        "keypoints_px": np.full((2, 2), 5.0, "<f4").tobytes(),
        "landmark_ids": np.array([3, -1], "<i8").tobytes()}), "BAD_FEATURES"),
    "unknown version": (lambda s: _keyframe_put(s, v=7), "UNSUPPORTED_VERSION"),
}


@pytest.mark.parametrize("case", sorted(BAD_PUTS))
def test_malformed_keyframe_puts_are_rejected_with_an_event(served, synthetic_scene, case):
    _, port, client, events = served
    build, code = BAD_PUTS[case]
    with raw_session(port) as session:
        session.put(wire.keys.keyframe("reloc", MAP, 90), build(synthetic_scene), congestion_control=BLOCK)
    events.wait("keyframe_rejected", id=90, code=code)
    events.seen.clear()
    assert 90 not in [i.id for i in client.keyframes()]
