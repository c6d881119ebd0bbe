"""The wire protocol: round trips of every message and one ErrorCode per class of malformed
input (no zenoh needed)."""

import copy
import math
import subprocess
import sys
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reloc_client import protocol as P
from reloc_client.protocol import ErrorCode as E

ROOT = Path(__file__).resolve().parents[1]

RNG_SEED = 0


# -- valid messages ---------------------------------------------------------------------------

def random_pose(rng: np.random.Generator) -> P.WirePose:
    q = rng.normal(size=4)
    return P.WirePose.from_tq(rng.normal(size=3).tolist(), (q / np.linalg.norm(q)).tolist())


CAMERA = P.WireCamera("radtan", 8, 6, 5.0, 5.5, 3.5, 2.5, (0.1, -0.01, 0.001, 0.002))
IMAGE = P.WireImage(P.ImageFormat.MONO8, 8, 6, bytes(range(48)))


def png_bytes(width: int = 8, height: int = 6, dtype=np.uint8) -> bytes:
    ok, buf = cv2.imencode(".png", np.zeros((height, width), dtype))
    assert ok
    return buf.tobytes()


def jpeg_bytes(width: int = 8, height: int = 6, progressive: bool = False) -> bytes:
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else []
    ok, buf = cv2.imencode(".jpg", np.full((height, width, 3), 128, np.uint8), params)
    assert ok
    return buf.tobytes()


def features(rng: np.random.Generator, n: int = 5) -> P.WireFeatures:
    pts = rng.normal(size=(n, 3))
    pts[1] = np.nan
    ids = np.arange(n) * 3
    ids[1] = -1
    return P.WireFeatures(rng.uniform(0, 8, size=(n, 2)), ids, pts)


def _pose_covariance(rng: np.random.Generator) -> tuple[float, ...]:
    """A full-rank 6x6 pose covariance, 36 row-major floats (cm and tenths of a degree)."""
    a = rng.normal(size=(6, 6)) * np.array([0.01, 0.02, 0.01, 0.003, 0.002, 0.004])[:, None]
    c = a @ a.T
    return tuple(float(v) for v in (0.5 * (c + c.T)).ravel())


POSE_COVARIANCE = _pose_covariance(np.random.default_rng(3))


def all_messages() -> list[P.Message]:
    rng = np.random.default_rng(RNG_SEED)
    pose = random_pose(rng)
    hyp = P.Hypothesis(random_pose(rng), "sbi+p3p", 0.5, 30, 60, 1.2, tuple(np.eye(6).ravel()),
                       (3, 4))
    depth = P.WireDepth.from_metres(rng.uniform(0.5, 3, size=(6, 8)))
    return [
        P.KeyframePut(0, IMAGE, pose, camera_id="cam0"),
        P.KeyframePut(2**63 - 1, IMAGE, pose, camera=CAMERA, timestamp=12.5,
                      features=features(rng), depth=depth),
        P.KeyframePut(7, P.WireImage.from_bytes(png_bytes()), pose, camera_id="c",
                      features=P.WireFeatures(np.zeros((0, 2)))),
        P.KeyframePut(8, P.WireImage.from_bytes(jpeg_bytes()), pose, camera=CAMERA,
                      depth=P.WireDepth(P.DepthFormat.PNG, 8, 6, png_bytes(dtype=np.uint16), 2e-4)),
        P.KeyframeInfo(3, CAMERA, pose),
        P.KeyframeInfo(4, CAMERA, pose, camera_id="cam0", timestamp=1.0, num_landmarks=9,
                       image=IMAGE),
        P.KeyframePut(9, IMAGE, pose, camera_id="cam0", pose_covariance=POSE_COVARIANCE),
        P.KeyframeInfo(9, CAMERA, pose, camera_id="cam0", pose_covariance=POSE_COVARIANCE),
        P.CameraPut("cam0", CAMERA),
        P.CameraPut("pin", P.WireCamera("pinhole", 640, 480, 500.0, 500.0, 319.5, 239.5)),
        P.RelocalizeRequest(IMAGE, camera_id="cam0"),
        P.RelocalizeRequest(P.WireImage.from_bytes(jpeg_bytes(progressive=True)), camera=CAMERA,
                            method="bow+p3p,sbi+esm", prior=P.Prior(pose, 3.0), hypotheses=4,
                            request_id="q-1", timestamp=5.0),
        P.RelocalizeReply(P.ReplyStatus.NOT_RELOCALIZED, "sbi+esm", reason="too few inliers"),
        P.RelocalizeReply(P.ReplyStatus.BUSY, reason="queue full"),
        P.RelocalizeReply(P.ReplyStatus.OK, "bow+p3p", pose, tuple(rng.normal(size=36)), 0.9, 100,
                          150, 0.8, (17, 18), 52, {"decode": 0.01, "total": 0.05}, "",
                          (hyp, P.Hypothesis(pose)), "q-1", 5.0),
        P.TrainRequest(),
        P.TrainRequest("ferns", "r2"),
        P.TrainReply(True, "job-1"),
        P.TrainReply(False, reason="map is empty"),
        P.Event(P.EventKind.TRAIN_PROGRESS, "lab", 1.7e9,
                {"job_id": "job-1", "fraction": 0.5, "stage": "warps", "nested": {"a": [1, None]}}),
        P.Event(P.EventKind.KEYFRAME_ADDED, "lab", 0.0),
        P.StatusReply("lab", "drone1", 10, 2000, True, 12),
        P.StatusReply("lab", "drone1", 10, 2000, False, 12, ("sbi+p3p", "ferns"), "sbi+p3p",
                      ("cam0",), True, 3.5, {"relocalize_ok": 3}, {"p50": 0.04, "p99": 0.1}),
        P.StatusReply("phone", "drone1", 3, 90, True, 4,
                      calibration_sigma={"focal_rel": 0.02, "radial_px": 6.0}),
        P.ErrorReply(E.BAD_POSE, "relocalize.prior.world_from_cam.q: expected a unit quaternion"),
    ]


@pytest.mark.parametrize("message", all_messages(), ids=lambda m: type(m).__name__)
def test_round_trip(message):
    data = message.encode()
    decoded = type(message).decode(data)
    assert decoded == message
    assert decoded.encode() == data


def test_decoded_values_keep_their_meaning():
    rng = np.random.default_rng(RNG_SEED)
    feats = features(rng, 7)
    kf = P.KeyframePut(1, IMAGE, random_pose(rng), camera=CAMERA, features=feats)
    back = P.KeyframePut.decode(kf.encode())
    assert back.features.keypoints_px.dtype == np.float32
    np.testing.assert_array_equal(back.features.landmark_ids, feats.landmark_ids)
    expected = np.arange(48, dtype=np.uint8).reshape(6, 8)
    np.testing.assert_array_equal(back.image.to_array(), expected)
    assert np.isnan(back.features.points_world[1]).all()


def test_depth_metres_round_trip():
    depth_m = np.array([[0.5, np.nan], [2.0, 65.0]])
    back = P.WireDepth.from_metres(depth_m).to_metres()
    np.testing.assert_allclose(back, depth_m, atol=5e-4)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
       st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
           lambda q: math.sqrt(sum(x * x for x in q)) > 1e-2))
def test_pose_matrix_round_trip(t, q):
    q = np.array(q) / np.linalg.norm(q)
    pose = P.WirePose.from_tq(t, q)
    m = pose.matrix()
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
    again = P.WirePose.from_matrix(m)
    np.testing.assert_allclose(again.matrix(), m, atol=1e-12)
    # q and -q are the same rotation; from_matrix picks w >= 0
    assert again.q[3] >= 0
    np.testing.assert_allclose(np.abs(np.dot(again.q, pose.q)), 1.0, atol=1e-9)


def test_quaternion_matches_reloc_service_geometry():
    from reloc_service.core.geometry import quat_xyzw_to_matrix

    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        np.testing.assert_allclose(P.quat_xyzw_to_rotation(q), quat_xyzw_to_matrix(q), atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(status=st.sampled_from(list(P.ReplyStatus)),
       confidence=st.floats(0, 1), inliers=st.integers(0, 10**6),
       rms=st.none() | st.floats(0, 1e3), ids=st.lists(st.integers(0, 2**63 - 1), max_size=5),
       timings=st.dictionaries(st.text(max_size=10), st.floats(0, 10), max_size=4),
       reason=st.text(max_size=50), version=st.integers(0, 2**40))
def test_reply_round_trip_property(status, confidence, inliers, rms, ids, timings, reason, version):
    pose = P.WirePose((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)) if status is P.ReplyStatus.OK else None
    reply = P.RelocalizeReply(status, "m", pose, None, confidence, inliers, inliers, rms,
                              tuple(ids), version, timings, reason)
    assert P.RelocalizeReply.decode(reply.encode()) == reply


# -- malformed input: each class has its code ------------------------------------------------

def valid_request() -> dict:
    rng = np.random.default_rng(RNG_SEED)
    msg = P.RelocalizeRequest(IMAGE, camera=CAMERA, prior=P.Prior(random_pose(rng), 2.0),
                              method="sbi+p3p", hypotheses=2)
    return msgpack.unpackb(msg.encode(), raw=False)


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def decode_error(data: bytes, cls=P.RelocalizeRequest, limits=P.DEFAULT_LIMITS) -> P.ProtocolError:
    with pytest.raises(P.ProtocolError) as info:
        cls.decode(data, limits)
    return info.value


def mutated(path: tuple, value=None, delete: bool = False) -> bytes:
    obj = copy.deepcopy(valid_request())
    node = obj
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return pack(obj)


def test_valid_request_decodes():
    P.RelocalizeRequest.decode(pack(valid_request()))


@pytest.mark.parametrize("data, code", [
    (b"", E.BAD_MSGPACK),
    (b"\xc1", E.BAD_MSGPACK),                       # never-used msgpack byte
    (b"\x81\xa1v", E.BAD_MSGPACK),                  # truncated
    (pack({"v": 1}) + b"\x00", E.BAD_MSGPACK),       # trailing bytes
    (b"\x81\xa1v\xc4\x01\xff" + b"\xa2\xff\xfe", E.BAD_MSGPACK),
    (pack([1, 2, 3]), E.NOT_A_MAP),
    (pack("hello"), E.NOT_A_MAP),
    (pack({1: 1}), E.NOT_A_MAP),
    (pack({"image": {}}), E.MISSING_FIELD),          # missing v
    (pack({"v": 2}), E.UNSUPPORTED_VERSION),
    (pack({"v": "1"}), E.UNSUPPORTED_VERSION),
    (pack({"v": True}), E.UNSUPPORTED_VERSION),
])
def test_envelope_errors(data, code):
    assert decode_error(data).code is code


def test_bad_msgpack_string_is_refused():
    data = b"\x82\xa1v\x01\xa5image\xa2\xff\xfe"  # str with invalid UTF-8
    assert decode_error(data).code is E.BAD_MSGPACK


@pytest.mark.parametrize("path, value, delete, code", [
    (("image",), None, True, E.MISSING_FIELD),
    (("image",), None, False, E.MISSING_FIELD),             # nil = absent
    (("image", "data"), None, True, E.MISSING_FIELD),
    (("camera",), None, True, E.MISSING_FIELD),             # neither camera nor camera_id
    (("camera_id",), "cam0", False, E.BAD_VALUE),           # both
    (("extra",), 1, False, E.UNKNOWN_FIELD),
    (("prior", "extra"), 1, False, E.UNKNOWN_FIELD),
    (("hypotheses",), "3", False, E.WRONG_TYPE),
    (("hypotheses",), 2.0, False, E.WRONG_TYPE),
    (("hypotheses",), True, False, E.WRONG_TYPE),
    (("hypotheses",), 0, False, E.BAD_VALUE),
    (("hypotheses",), 33, False, E.BAD_VALUE),
    (("method",), 5, False, E.WRONG_TYPE),
    (("method",), "sbi+p3p,,ferns", False, E.BAD_VALUE),
    (("method",), "", False, E.BAD_VALUE),
    (("image",), b"jpeg", False, E.WRONG_TYPE),
    (("image", "data"), "text", False, E.WRONG_TYPE),
    (("prior", "radius_m"), -1, False, E.BAD_VALUE),
    (("prior", "radius_m"), float("nan"), False, E.BAD_VALUE),
    (("prior", "world_from_cam", "t", 0), float("nan"), False, E.BAD_POSE),
    (("prior", "world_from_cam", "t", 1), float("inf"), False, E.BAD_POSE),
    (("prior", "world_from_cam", "q"), [0.0, 0.0, 0.0, 1.01], False, E.BAD_POSE),
    (("prior", "world_from_cam", "q"), [0.0, 0.0, 0.0, 0.0], False, E.BAD_POSE),
    (("prior", "world_from_cam", "q"), [0.0, 0.0, 1.0], False, E.BAD_POSE),
    (("prior", "world_from_cam", "q"), [0.0, 0.0, "a", 1.0], False, E.WRONG_TYPE),
    (("prior", "world_from_cam", "t"), None, True, E.MISSING_FIELD),
    (("camera", "model"), "fisheye", False, E.BAD_CAMERA),
    (("camera", "distortion"), [0.1], False, E.BAD_CAMERA),
    (("camera", "fx"), 0.0, False, E.BAD_CAMERA),
    (("camera", "width"), -8, False, E.BAD_CAMERA),
    (("camera", "width"), 9, False, E.BAD_IMAGE),           # camera size != image size
    (("camera", "fy"), "5", False, E.WRONG_TYPE),
    (("image", "format"), "bmp", False, E.BAD_IMAGE),
    (("image", "data"), b"", False, E.BAD_IMAGE),
    (("image", "data"), bytes(47), False, E.BAD_IMAGE),     # mono8 8x6 needs 48 bytes
    (("image", "width"), 0, False, E.BAD_VALUE),
    (("image", "width"), 8.0, False, E.WRONG_TYPE),
])
def test_field_errors(path, value, delete, code):
    err = decode_error(mutated(path, value, delete))
    assert err.code is code, err


@pytest.mark.parametrize("camera_id", ["a/b", "", "@x", 3])
def test_bad_camera_id(camera_id):
    obj = valid_request()
    del obj["camera"]
    obj["camera_id"] = camera_id
    assert decode_error(pack(obj)).code is E.BAD_NAME


def test_error_message_names_field_and_expectation():
    err = decode_error(mutated(("prior", "radius_m"), -1))
    assert err.message == "relocalize.prior.radius_m: expected a positive number, got -1"
    assert str(err).startswith("BAD_VALUE: ")


@pytest.mark.parametrize("make_data, stated, code", [
    (lambda: png_bytes(8, 6), (8, 6), None),
    (lambda: png_bytes(8, 6), (8, 7), E.BAD_IMAGE),
    (lambda: jpeg_bytes(8, 6), (8, 6), None),
    (lambda: jpeg_bytes(8, 6, progressive=True), (8, 6), None),
    (lambda: jpeg_bytes(8, 6), (6, 8), E.BAD_IMAGE),
    (lambda: png_bytes(8, 6)[:20], (8, 6), E.BAD_IMAGE),     # truncated header
    (lambda: b"\xff\xd8\xff\xd9", (8, 6), E.BAD_IMAGE),       # JPEG without frame header
    (lambda: b"GIF89a" + bytes(40), (8, 6), E.BAD_IMAGE),
])
@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_image_container(make_data, stated, code, fmt):
    data = make_data()
    actual = "png" if data.startswith(b"\x89PNG") else "jpeg" if data[:2] == b"\xff\xd8" else "?"
    obj = valid_request()
    obj["image"] = {"format": fmt, "width": stated[0], "height": stated[1], "data": data}
    obj["camera"]["width"], obj["camera"]["height"] = stated
    if code is None and fmt == actual:
        assert P.RelocalizeRequest.decode(pack(obj)).image.data == data
    else:  # wrong container for the stated format, or a bad container
        assert decode_error(pack(obj)).code is E.BAD_IMAGE


def test_payload_too_large():
    data = pack(valid_request())
    limits = P.Limits(max_payload_bytes=len(data) - 1)
    assert decode_error(data, limits=limits).code is E.PAYLOAD_TOO_LARGE
    P.RelocalizeRequest.decode(data, P.Limits(max_payload_bytes=len(data)))


def test_image_too_large():
    data = pack(valid_request())
    assert decode_error(data, limits=P.Limits(max_image_pixels=47)).code is E.IMAGE_TOO_LARGE
    # refused before the data length is even looked at
    obj = valid_request()
    obj["image"].update(width=100_000, height=100_000, data=b"x")
    assert decode_error(pack(obj)).code is E.IMAGE_TOO_LARGE


def kf_dict(**feature_fields) -> dict:
    rng = np.random.default_rng(RNG_SEED)
    msg = P.KeyframePut(5, IMAGE, random_pose(rng), camera_id="cam0", features=features(rng))
    obj = msgpack.unpackb(msg.encode(), raw=False)
    obj["features"].update(feature_fields)
    return obj


@pytest.mark.parametrize("fields, code", [
    ({"keypoints_px": bytes(12)}, E.BAD_FEATURES),                       # not a multiple of 8
    ({"landmark_ids": np.zeros(4, "<i8").tobytes()}, E.BAD_FEATURES),     # 4 ids, 5 keypoints
    ({"landmark_ids": np.full(5, -2, "<i8").tobytes()}, E.BAD_FEATURES),
    ({"points_world": np.zeros((6, 3), "<f8").tobytes()}, E.BAD_FEATURES),
    ({"points_world": np.array([[0, np.nan, 0]] * 5, "<f8").tobytes()}, E.BAD_FEATURES),
    ({"keypoints_px": np.full((5, 2), np.inf, "<f4").tobytes()}, E.BAD_FEATURES),
    ({"keypoints_px": [[1.0, 2.0]] * 5}, E.WRONG_TYPE),
])
def test_feature_errors(fields, code):
    assert decode_error(pack(kf_dict(**fields)), P.KeyframePut).code is code


def test_too_many_features():
    data = pack(kf_dict())
    err = decode_error(data, P.KeyframePut, P.Limits(max_features=4))
    assert err.code is E.PAYLOAD_TOO_LARGE
    P.KeyframePut.decode(data, P.Limits(max_features=5))


def test_a_keyframe_pose_covariance_round_trips_exactly():
    rng = np.random.default_rng(RNG_SEED)
    for cls, msg in ((P.KeyframePut, P.KeyframePut(1, IMAGE, random_pose(rng), camera_id="c",
                                                     pose_covariance=POSE_COVARIANCE)),
                     (P.KeyframeInfo, P.KeyframeInfo(1, CAMERA, random_pose(rng),
                                                     pose_covariance=POSE_COVARIANCE))):
        back = cls.decode(msg.encode())
        assert back.pose_covariance == POSE_COVARIANCE
    without = P.KeyframePut.decode(P.KeyframePut(2, IMAGE, random_pose(rng),
                                                 camera_id="c").encode())
    assert without.pose_covariance is None
    assert "pose_covariance" not in msgpack.unpackb(
        P.KeyframePut(2, IMAGE, random_pose(rng), camera_id="c").encode(), raw=False)


def _bad_covariances() -> list[tuple[object, str]]:
    asymmetric = np.diag(np.full(6, 1e-4))
    asymmetric[0, 1] = 1e-5
    indefinite = np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, -1e-6])
    return [(asymmetric.ravel().tolist(), "not symmetric"),
            (indefinite.ravel().tolist(), "not positive semi-definite"),
            ([1e-4] * 35, "an array of 36 numbers"),
            ([float("nan")] + [0.0] * 35, "a finite number"),
            ("not numbers", "an array of 36 numbers")]


@pytest.mark.parametrize("value, says", _bad_covariances(),
                         ids=["asymmetric", "indefinite", "35", "nan", "str"])
def test_bad_pose_covariances_are_refused_saying_why(value, says):
    obj = kf_dict()
    obj["pose_covariance"] = value
    err = decode_error(pack(obj), P.KeyframePut)
    assert err.code in (E.BAD_VALUE, E.WRONG_TYPE)
    assert err.message.startswith("keyframe.pose_covariance") and says in err.message, err
    with pytest.raises(P.ProtocolError, match="pose_covariance"):   # nor does encode make one
        P.KeyframePut(1, IMAGE, P.WirePose.from_matrix(np.eye(4)), camera_id="c",
                      pose_covariance=tuple(np.ravel(np.asarray(value, dtype=object)))).encode()


def test_depth_errors():
    obj = kf_dict()
    obj["depth"] = {"format": "png", "width": 8, "height": 6, "data": png_bytes(8, 6),
                    "metres_per_unit": 0.001}   # 8-bit PNG is not a depth map
    assert decode_error(pack(obj), P.KeyframePut).code is E.BAD_IMAGE
    obj["depth"].update(format="mono16", data=bytes(95))
    assert decode_error(pack(obj), P.KeyframePut).code is E.BAD_IMAGE
    obj["depth"].update(data=bytes(96), metres_per_unit=0)
    assert decode_error(pack(obj), P.KeyframePut).code is E.BAD_VALUE
    obj["depth"].update(width=4, height=12, metres_per_unit=0.001)  # size != image size
    assert decode_error(pack(obj), P.KeyframePut).code is E.BAD_IMAGE


@pytest.mark.parametrize("kf_id, code", [(-1, E.BAD_VALUE), (2**63, E.BAD_VALUE),
                                         ("3", E.WRONG_TYPE), (1.0, E.WRONG_TYPE)])
def test_keyframe_id(kf_id, code):
    obj = kf_dict()
    obj["id"] = kf_id
    assert decode_error(pack(obj), P.KeyframePut).code is code


def test_reply_pose_iff_ok():
    ok = msgpack.unpackb(P.RelocalizeReply(P.ReplyStatus.OK, "m", P.WirePose(
        (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))).encode())
    del ok["world_from_cam"]
    assert decode_error(pack(ok), P.RelocalizeReply).code is E.BAD_VALUE
    bad_status = {"v": 1, "status": "maybe"}
    assert decode_error(pack(bad_status), P.RelocalizeReply).code is E.BAD_VALUE
    bad_cov = {"v": 1, "status": "not_relocalized", "covariance": [0.0] * 35}
    assert decode_error(pack(bad_cov), P.RelocalizeReply).code is E.BAD_VALUE
    bad_conf = {"v": 1, "status": "not_relocalized", "confidence": 1.5}
    assert decode_error(pack(bad_conf), P.RelocalizeReply).code is E.BAD_VALUE


def test_encode_refuses_what_decode_would_refuse():
    with pytest.raises(P.ProtocolError) as info:
        P.RelocalizeRequest(IMAGE, camera_id="cam0", camera=CAMERA).encode()
    assert info.value.code is E.BAD_VALUE
    with pytest.raises(P.ProtocolError):
        P.Event(P.EventKind.TRAIN_DONE, "bad/map", 0.0).encode()
    with pytest.raises(P.ProtocolError):
        P.TrainReply(True).encode()  # accepted without a job id


def test_error_reply_unknown_code_is_internal():
    data = pack({"v": 1, "error": {"code": "FROM_THE_FUTURE", "message": "m"}})
    err = P.ErrorReply.decode(data)
    assert err.code is E.INTERNAL and "FROM_THE_FUTURE" in err.message
    assert P.ErrorReply.decode(P.encode_error(E.BUSY, "later")).code is E.BUSY


def test_every_error_code_is_upper_snake_and_documented():
    doc = (ROOT / "docs" / "protocol.md").read_text()
    for code in E:
        assert code.value == code.name
        assert f"`{code.value}`" in doc, f"{code.value} missing from docs/protocol.md"


# -- names and keys ----------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["", "a/b", "a*", "**", "$x", "a#b", "q?", "has space",
                                  "tab\t", "@live", "x" * 129, 5, None])
def test_bad_map_names(name):
    with pytest.raises(P.ProtocolError) as info:
        P.keys.relocalize("reloc", name)
    assert info.value.code is E.BAD_NAME
    obj = {"v": 1, "kind": "keyframe_added", "map": name, "time": 0.0}
    if name is not None:
        assert decode_error(pack(obj), P.Event).code in (E.BAD_NAME,)


@pytest.mark.parametrize("prefix", ["", "/reloc", "reloc/", "a//b", "re*", "@x"])
def test_bad_prefixes(prefix):
    with pytest.raises(P.ProtocolError) as info:
        P.keys.status(prefix, "lab")
    assert info.value.code is E.BAD_NAME


def test_keys():
    k = P.keys
    assert k.relocalize("reloc", "lab") == "reloc/lab/relocalize"
    assert k.train("a/b", "lab") == "a/b/lab/train"
    assert k.status("reloc", "lab") == "reloc/lab/status"
    assert k.events("reloc", "lab") == "reloc/lab/events"
    assert k.keyframe("reloc", "lab", 17) == "reloc/lab/keyframes/17"
    assert k.keyframes("reloc", "lab") == "reloc/lab/keyframes/**"
    assert k.camera("reloc", "lab", "cam0") == "reloc/lab/cameras/cam0"
    assert k.cameras("reloc", "lab") == "reloc/lab/cameras/**"
    assert k.liveliness("reloc", "drone-1", "lab") == "reloc/@live/drone-1/lab"
    assert k.liveliness_all("reloc") == "reloc/@live/*/*"
    assert k.parse_keyframe("a/b", "a/b/lab/keyframes/17") == ("lab", 17)
    assert k.parse_camera("reloc", "reloc/lab/cameras/cam0") == ("lab", "cam0")
    assert k.parse_liveliness("reloc", "reloc/@live/drone-1/lab") == ("drone-1", "lab")
    assert k.resident("reloc", "drone-1", "lab") == "reloc/@live/drone-1/lab/resident"
    assert k.resident_all("reloc") == "reloc/@live/*/*/resident"
    assert k.parse_resident("reloc", "reloc/@live/drone-1/lab/resident") == ("drone-1", "lab")
    for bad in ["reloc/@live/drone-1/lab", "reloc/@live/lab/resident"]:
        with pytest.raises(P.ProtocolError):
            k.parse_resident("reloc", bad)
    for bad in ["reloc/lab/keyframes/017", "reloc/lab/keyframes/-1", "reloc/lab/keyframes/x",
                "reloc/lab/cameras/3", "other/lab/keyframes/3", "reloc/lab/keyframes/3/4"]:
        with pytest.raises(P.ProtocolError):
            k.parse_keyframe("reloc", bad)
    with pytest.raises(P.ProtocolError):
        k.keyframe("reloc", "lab", -1)


# -- helpers and invariants --------------------------------------------------------------------

def test_image_from_bytes_and_array():
    png = P.WireImage.from_bytes(png_bytes(20, 10))
    assert (png.format, png.width, png.height) == (P.ImageFormat.PNG, 20, 10)
    jpg = P.WireImage.from_bytes(jpeg_bytes(33, 17))
    assert (jpg.format, jpg.width, jpg.height) == (P.ImageFormat.JPEG, 33, 17)
    with pytest.raises(P.ProtocolError):
        P.WireImage.from_bytes(b"not an image")
    with pytest.raises(P.ProtocolError):
        P.WireImage.from_array(np.zeros((4, 4, 3), np.uint8))
    arr = np.arange(12, dtype=np.uint8).reshape(3, 4)
    np.testing.assert_array_equal(P.WireImage.from_array(arr).to_array(), arr)


def test_pose_from_matrix_refuses_bad_matrices():
    m = np.eye(4)
    m[0, 1] = 0.1
    for bad in [m, np.full((4, 4), np.nan), np.eye(3), np.diag([1.0, 1.0, -1.0, 1.0])]:
        with pytest.raises(P.ProtocolError) as info:
            P.WirePose.from_matrix(bad)
        assert info.value.code is E.BAD_POSE


def test_quaternion_is_normalised():
    pose = P.WirePose.from_tq([0, 0, 0], [0, 0, 0, 1.0005])
    assert pose.q == (0.0, 0.0, 0.0, 1.0)


def test_camera_models_match_the_service():
    from reloc_service.core.cameras import CAMERA_MODELS

    assert {n: tuple(c.n_distortion) for n, c in CAMERA_MODELS.items()} == P.CAMERA_MODELS


def test_protocol_imports_no_heavy_modules():
    code = ("import sys; import reloc_client.protocol; "
            "print(','.join(m for m in ('cv2', 'scipy', 'poselib', 'zenoh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT / "clients"), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == ""


def test_worked_example_in_docs_decodes():
    import json
    import re

    blocks = re.findall(r"```json\n(.*?)```", (ROOT / "docs" / "protocol.md").read_text(), re.S)
    request, reply = (json.loads(b) for b in blocks[:2])
    request["image"]["data"] = jpeg_bytes(640, 480)
    decoded = P.RelocalizeRequest.decode(pack(request))
    assert decoded.prior.radius_m == 3.0 and decoded.method == "bow+p3p,sbi+esm"
    answer = P.RelocalizeReply.decode(pack(reply))
    assert answer.status is P.ReplyStatus.OK and len(answer.covariance) == 36


@pytest.mark.parametrize("message,field", [
    (P.RelocalizeRequest(IMAGE, camera=CAMERA), "image"),
    (P.RelocalizeRequest(IMAGE, camera=CAMERA), "camera"),
    (P.RelocalizeRequest(IMAGE, camera=CAMERA), "method"),
    (P.RelocalizeRequest(IMAGE, camera=CAMERA), "prior"),
    (P.RelocalizeRequest(IMAGE, camera_id="cam0"), "camera_id"),
    (P.TrainRequest("ferns", "r2"), "method"),
])
def test_a_value_nested_a_thousand_levels_deep_gets_a_named_error(message, field):
    """A crafted request nesting arrays ~1,000 deep in one field is refused with that
    field's error code and a short description, not a recursion error (the service's
    INTERNAL)."""
    deep: object = 1
    for _ in range(1000):
        deep = [deep]
    body = msgpack.unpackb(message.encode(), raw=False)
    body[field] = deep
    with pytest.raises(P.ProtocolError) as caught:
        type(message).decode(msgpack.packb(body))
    assert caught.value.code in (E.WRONG_TYPE, E.BAD_VALUE, E.BAD_NAME) and field in str(caught.value)
    assert len(str(caught.value)) < 300
