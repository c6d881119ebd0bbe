"""The wire protocol: round trips of every message, names and keys, helpers and invariants (no
zenoh needed); tests/test_protocol_errors.py has the malformed input."""

import math
import subprocess
import sys

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
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


# -- valid messages ---------------------------------------------------------------------------

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
        P.StatusReply("lab", "drone1", 10, 2000, True, 12,
                      keyframe_pose_sigma={"position_m": 0.004, "rotation_deg": 0.2,
                                           "keyframes": 27.0}),
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


def test_protocol_and_client_errors_import_no_heavy_modules():
    code = ("import sys; import reloc_client.protocol; "
            "from reloc_client import ServiceBusy, ServiceError; "
            "assert issubclass(ServiceBusy, ServiceError); "
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
