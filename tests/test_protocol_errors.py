"""The wire protocol refuses malformed input: one ErrorCode per class, a message that names the
field and what was expected (no zenoh needed)."""

import copy

import msgpack
import numpy as np
import pytest
from protocol_support import (
    CAMERA,
    IMAGE,
    POSE_COVARIANCE,
    ROOT,
    decode_error,
    features,
    jpeg_bytes,
    pack,
    png_bytes,
    random_pose,
)
from reloc_client import protocol as P
from reloc_client.protocol import ErrorCode as E

RNG_SEED = 0


# -- malformed input: each class has its code ------------------------------------------------

def valid_request() -> dict:
    rng = np.random.default_rng(RNG_SEED)
    msg = P.RelocalizeRequest(IMAGE, camera=CAMERA, prior=P.Prior(random_pose(rng), 2.0),
                              method="sbi+p3p", hypotheses=2)
    return msgpack.unpackb(msg.encode(), raw=False)


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
