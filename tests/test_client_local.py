"""RelocClient against a tiny fake service declared here: two real Zenoh sessions on
loopback (free port, multicast scouting off). The real service is tested elsewhere."""

import json
import re
import socket
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from reloc_client import protocol as P  # noqa: E402 (after the importorskip)
from reloc_client.client import (  # noqa: E402 (after the importorskip)
    NoReplyError,
    RelocClient,
    RelocStatus,
    ServiceBusy,
    ServiceError,
)

ROOT = Path(__file__).resolve().parents[1]

MAP = "lab"
CAMERA = {"model": "pinhole", "width": 8, "height": 6, "fx": 5.0, "fy": 5.0, "cx": 3.5, "cy": 2.5,
          "distortion": []}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class FakeService:
    """Answers like the service would, and records what it received."""

    def __init__(self, session: "zenoh.Session", prefix: str = "reloc") -> None:
        self.session, self.prefix = session, prefix
        self.requests: list[P.RelocalizeRequest] = []
        self.puts: list[tuple[str, bytes | None]] = []
        self.mode = "ok"
        self.port = 0
        k = P.keys
        self.entities = [
            session.declare_queryable(k.relocalize(prefix, MAP), self.on_relocalize),
            session.declare_queryable(k.status(prefix, MAP), self.on_status),
            session.declare_queryable(k.train(prefix, MAP), self.on_train),
            session.declare_queryable(k.keyframes(prefix, MAP), self.on_keyframes),
            session.declare_queryable(k.cameras(prefix, MAP), self.on_cameras),
            session.declare_subscriber(k.keyframes(prefix, MAP), self.on_put),
            session.declare_subscriber(k.cameras(prefix, MAP), self.on_put),
            session.liveliness().declare_token(k.liveliness(prefix, "fake-1", MAP)),
        ]

    def on_relocalize(self, query: "zenoh.Query") -> None:
        try:
            request = P.RelocalizeRequest.decode(query.payload.to_bytes())
        except P.ProtocolError as exc:
            query.reply_err(P.ErrorReply.from_exception(exc).encode())
            return
        self.requests.append(request)
        if self.mode == "slow":
            time.sleep(1.5)
        if self.mode == "error":
            query.reply_err(P.encode_error(P.ErrorCode.UNKNOWN_METHOD, "no method 'x'"))
        elif self.mode == "busy_error":
            query.reply_err(P.encode_error(P.ErrorCode.BUSY, "queue full"))
        elif self.mode == "busy_status":
            busy = P.RelocalizeReply(P.ReplyStatus.BUSY, reason="full")
            query.reply(query.key_expr, busy.encode())
        elif self.mode == "not_relocalized":
            query.reply(query.key_expr, P.RelocalizeReply(
                P.ReplyStatus.NOT_RELOCALIZED, "sbi+esm", reason="too few inliers").encode())
        else:
            pose = request.prior.world_from_cam if request.prior else P.WirePose(
                (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0))
            query.reply(query.key_expr, P.RelocalizeReply(
                P.ReplyStatus.OK, request.method or "sbi+p3p", pose,
                tuple(np.eye(6).ravel() * 1e-4), 0.9, 40, 50, 0.7, (3,), 7, {"total": 0.01},
                request_id=request.request_id,
                hypotheses=(P.Hypothesis(pose, "x"),) * (request.hypotheses - 1)).encode())

    def on_status(self, query: "zenoh.Query") -> None:
        query.reply(query.key_expr, P.StatusReply(MAP, "fake-1", 2, 10, False, 7,
                                                  ("sbi+p3p",), "sbi+p3p").encode())

    def on_train(self, query: "zenoh.Query") -> None:
        P.TrainRequest.decode(query.payload.to_bytes())
        query.reply(query.key_expr, P.TrainReply(True, "job-9").encode())
        threading.Thread(target=self.publish_training, daemon=True).start()

    def publish_training(self) -> None:
        events = P.keys.events(self.prefix, MAP)
        time.sleep(0.05)
        other_job = P.Event(P.EventKind.TRAIN_DONE, MAP, 1.0, {"job_id": "other"})
        self.session.put(events, other_job.encode())
        self.session.put(events, P.Event(P.EventKind.TRAIN_PROGRESS, MAP, 1.0,
                                         {"job_id": "job-9", "fraction": 0.5}).encode())
        self.session.put(events, b"garbage is ignored")
        final = (P.Event(P.EventKind.TRAIN_FAILED, MAP, 2.0,
                         {"job_id": "job-9", "code": "STORAGE_ERROR", "message": "disk full"})
                 if self.mode == "train_fails" else
                 P.Event(P.EventKind.TRAIN_DONE, MAP, 2.0, {"job_id": "job-9"}))
        self.session.put(events, final.encode())

    def on_keyframes(self, query: "zenoh.Query") -> None:
        with_image = query.parameters.get("image") == "true"
        for kf_id in (4, 2):
            info = P.KeyframeInfo(kf_id, P.WireCamera.from_dict(CAMERA),
                                  P.WirePose((0.0, 0.0, float(kf_id)), (0.0, 0.0, 0.0, 1.0)),
                                  image=P.WireImage.from_array(np.zeros((6, 8), np.uint8))
                                  if with_image else None)
            query.reply(P.keys.keyframe(self.prefix, MAP, kf_id), info.encode())

    def on_cameras(self, query: "zenoh.Query") -> None:
        for key, payload in list(self.puts):
            if "/cameras/" in key and payload is not None:
                query.reply(key, payload)

    def on_put(self, sample: "zenoh.Sample") -> None:
        payload = sample.payload.to_bytes() if sample.kind == zenoh.SampleKind.PUT else None
        self.puts.append((str(sample.key_expr), payload))
        what, ident = str(sample.key_expr).split("/")[-2:]   # acknowledged like the service
        kind = P.EventKind.CAMERA_ADDED if what == "cameras" else P.EventKind.KEYFRAME_ACCEPTED
        event = P.Event(kind, MAP, 1.0, {"id": ident if what == "cameras" else int(ident)})
        self.session.put(P.keys.events(self.prefix, MAP), event.encode())


@pytest.fixture(scope="module")
def endpoint():
    port = free_port()
    conf = zenoh.Config.from_json5(json.dumps({
        "mode": "peer", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}}}))
    with zenoh.open(conf) as session:
        service = FakeService(session)
        service.port = port
        yield f"tcp/127.0.0.1:{port}", service


@pytest.fixture
def client(endpoint):
    ep, service = endpoint
    service.mode = "ok"
    with RelocClient(ep, map=MAP, timeout=3.0) as c:
        time.sleep(0.1)  # let declarations propagate
        yield c, service


def test_relocalize_ok(client):
    c, service = client
    image = np.arange(48, dtype=np.uint8).reshape(6, 8)
    prior = (np.diag([1.0, -1.0, -1.0, 1.0]), 2.5)
    result = c.relocalize(image, camera=CAMERA, method="bow+p3p,sbi+esm", prior=prior,
                          hypotheses=3, request_id="r1")
    assert result.ok and result.status is RelocStatus.OK
    np.testing.assert_allclose(result.world_from_cam, prior[0], atol=1e-12)
    assert result.covariance.shape == (6, 6)
    assert result.method == "bow+p3p,sbi+esm" and result.request_id == "r1"
    assert len(result.hypotheses) == 2 and result.round_trip_s > 0
    sent = service.requests[-1]
    assert sent.image.format is P.ImageFormat.MONO8
    np.testing.assert_array_equal(sent.image.to_array(), image)
    assert sent.prior.radius_m == 2.5 and sent.hypotheses == 3
    json.dumps(result.to_dict())  # JSON-ready


def test_relocalize_sends_files_as_is(client, tmp_path):
    c, service = client
    path = tmp_path / "q.jpg"
    cv2.imwrite(str(path), np.full((6, 8), 100, np.uint8))
    assert c.relocalize(path, camera_id="cam0").ok
    sent = service.requests[-1]
    assert sent.image.format is P.ImageFormat.JPEG and sent.image.data == path.read_bytes()
    assert sent.camera_id == "cam0"


@pytest.mark.parametrize("mode, exc, code", [
    ("error", ServiceError, P.ErrorCode.UNKNOWN_METHOD),
    ("busy_error", ServiceBusy, P.ErrorCode.BUSY),
    ("busy_status", ServiceBusy, P.ErrorCode.BUSY),
])
def test_relocalize_errors(client, mode, exc, code):
    c, service = client
    service.mode = mode
    with pytest.raises(exc) as info:
        c.relocalize(np.zeros((6, 8), np.uint8), camera_id="cam0")
    assert info.value.code is code


def test_not_relocalized_is_a_result(client):
    c, service = client
    service.mode = "not_relocalized"
    result = c.relocalize(np.zeros((6, 8), np.uint8), camera_id="cam0")
    assert not result.ok and result.world_from_cam is None and "inliers" in result.reason


def test_protocol_error_reply_from_service(client):
    c, service = client
    # a camera that does not match the image is caught by the client before sending
    with pytest.raises(P.ProtocolError):
        c.relocalize(np.zeros((5, 8), np.uint8), camera=CAMERA)
    payload = P.RelocalizeRequest(P.WireImage.from_array(np.zeros((6, 8), np.uint8)),
                                  camera_id="cam0").encode()
    bad = payload.replace(b"\xa1v\x01", b"\xa1v\x02")  # v = 2
    with pytest.raises(ServiceError) as info:
        c._query_one(P.keys.relocalize("reloc", MAP), bad, None)
    assert info.value.code is P.ErrorCode.UNSUPPORTED_VERSION


def test_no_service_for_map(endpoint):
    with RelocClient(endpoint[0], map="nowhere", timeout=2.0) as c:
        start = time.monotonic()
        with pytest.raises(NoReplyError, match="nowhere"):
            c.status()
        assert time.monotonic() - start < 1.9  # no queryable: the answer is immediate


def test_slow_service_times_out(client):
    c, service = client
    service.mode = "slow"
    with pytest.raises(NoReplyError):
        c.relocalize(np.zeros((6, 8), np.uint8), camera_id="cam0", timeout=0.5)
    time.sleep(1.2)  # let the fake finish before the next test


def test_status_maps_keyframes(client):
    c, _ = client
    status = c.status()
    assert (status.keyframes, status.map_version, status.instance) == (2, 7, "fake-1")
    assert ("fake-1", MAP) in c.maps()
    kfs = c.keyframes()
    assert [k.id for k in kfs] == [2, 4] and all(k.image is None for k in kfs)
    assert kfs[1].world_from_cam.t == (0.0, 0.0, 4.0)
    assert all(k.image is not None for k in c.keyframes(images=True))


def test_puts_and_deletes(client):
    c, service = client
    before = len(service.puts)
    c.set_camera("cam0", CAMERA)
    rng = np.random.default_rng(0)
    feats = {"keypoints_px": rng.uniform(0, 6, (4, 2)), "landmark_ids": [1, 2, -1, 3]}
    cov = np.diag([1e-4, 4e-4, 9e-4, 1e-5, 2e-5, 3e-5])
    c.add_keyframe(11, np.zeros((6, 8), np.uint8), (np.zeros(3), [0, 0, 0, 1]), camera_id="cam0",
                   timestamp=3.0, features=feats, depth=np.full((6, 8), 1.5),
                   pose_covariance=cov)
    c.remove_keyframe(11)
    deadline = time.monotonic() + 2
    while len(service.puts) < before + 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    # separate subscribers: callbacks of different keys may run in any order
    (cam_key, cam), (kf_key, kf), (del_key, gone) = sorted(
        service.puts[before:before + 3], key=lambda kp: (kp[0], kp[1] is None))
    assert cam_key == "reloc/lab/cameras/cam0" and P.CameraPut.decode(cam).id == "cam0"
    put = P.KeyframePut.decode(kf)
    assert kf_key == "reloc/lab/keyframes/11" and put.id == 11 and put.timestamp == 3.0
    np.testing.assert_array_equal(put.features.landmark_ids, [1, 2, -1, 3])
    np.testing.assert_allclose(put.depth.to_metres(), 1.5)
    np.testing.assert_array_equal(np.reshape(put.pose_covariance, (6, 6)), cov)
    assert del_key == kf_key and gone is None


def test_a_bad_pose_covariance_raises_before_anything_is_sent(client):
    c, service = client
    before = len(service.puts)
    for bad, says in ((np.diag([1.0, 1, 1, 1, 1, -1]), "positive semi-definite"),
                      (np.eye(5), "(6, 6)")):
        with pytest.raises(ValueError, match=re.escape(says)):
            c.add_keyframe(12, np.zeros((6, 8), np.uint8), (np.zeros(3), [0, 0, 0, 1]),
                           camera_id="cam0", pose_covariance=bad)
    time.sleep(0.1)
    assert len(service.puts) == before


def test_train_wait(client):
    c, _ = client
    seen = []
    reply = c.train(wait=True, timeout=5.0, on_event=seen.append)
    assert reply.accepted and reply.job_id == "job-9"
    assert [e.kind for e in seen] == [P.EventKind.TRAIN_PROGRESS, P.EventKind.TRAIN_DONE]


def test_train_failure_raises(client):
    c, service = client
    service.mode = "train_fails"
    with pytest.raises(ServiceError) as info:
        c.train(wait=True, timeout=5.0)
    assert info.value.code is P.ErrorCode.STORAGE_ERROR and "disk full" in info.value.message


def test_client_validates_names():
    with pytest.raises(P.ProtocolError):
        RelocClient("tcp/127.0.0.1:1", map="a/b")


# -- the command line and the raw example, against the same fake -----------------------------

def write_dataset(root: Path) -> None:
    (root / "images").mkdir(parents=True)
    (root / "cameras.json").write_text(json.dumps({"cam0": CAMERA}))
    lines = ["# reloc dataset v1", "images/0.png cam0 0 0 0 0 0 0 1",
             "images/1.png cam0 1 0 0 0 0 0.7071068 0.7071068  # comment"]
    (root / "map.txt").write_text("\n".join(lines) + "\n")
    for i in range(2):
        cv2.imwrite(str(root / f"images/{i}.png"), np.full((6, 8), 50 * i, np.uint8))
    cv2.imwrite(str(root / "images/0_depth.png"), np.full((6, 8), 1000, np.uint16))
    (root / "depth.txt").write_text("images/0.png images/0_depth.png 0.001\n")


def test_cli_upload_and_relocalize(client, tmp_path, capsys):
    from reloc_client.cli import main

    _, service = client
    endpoint = f"tcp/127.0.0.1:{_port_of(service)}"
    write_dataset(tmp_path / "ds")
    before = len(service.puts)
    assert main(["--connect", endpoint, "--map", MAP, "upload", str(tmp_path / "ds")]) == 0
    deadline = time.monotonic() + 2
    while len(service.puts) < before + 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    puts = dict(service.puts[before:])
    assert sorted(puts) == ["reloc/lab/cameras/cam0", "reloc/lab/keyframes/0",
                            "reloc/lab/keyframes/1"]
    kf0 = P.KeyframePut.decode(puts["reloc/lab/keyframes/0"])
    assert kf0.depth.format is P.DepthFormat.PNG and kf0.depth.metres_per_unit == 0.001
    assert kf0.camera_id == "cam0"  # the fake listed the camera, so keyframes refer to it
    kf1 = P.KeyframePut.decode(puts["reloc/lab/keyframes/1"])
    assert kf1.world_from_cam.t == (1.0, 0.0, 0.0) and kf1.image.format is P.ImageFormat.PNG

    (tmp_path / "cam.json").write_text(json.dumps({"cam0": CAMERA}))
    capsys.readouterr()
    code = main(["--connect", endpoint, "--map", MAP, "relocalize",
                 str(tmp_path / "ds/images/1.png"), "--camera-json", str(tmp_path / "cam.json"),
                 "--method", "sbi+p3p"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["status"] == "ok" and out["method"] == "sbi+p3p"
    assert out["world_from_cam_tum"] == [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0]
    expected = [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]
    assert np.allclose(out["world_from_cam"], expected)
    assert main(["--connect", endpoint, "--map", "nowhere", "--timeout", "1", "status"]) == 3
    assert main(["--connect", endpoint, "maps"]) == 0
    assert {"instance": "fake-1", "map": MAP} in json.loads(capsys.readouterr().out)


def test_cli_refuses_a_bad_dataset(client, tmp_path, capsys):
    from reloc_client.cli import main

    _, service = client
    write_dataset(tmp_path / "ds")
    (tmp_path / "ds/map.txt").write_text("images/0.png cam0 0 0 0 0 0 0 2\n")
    code = main(["--connect", f"tcp/127.0.0.1:{_port_of(service)}", "--map", MAP, "upload",
                 str(tmp_path / "ds")])
    assert code == 2 and "map.txt:1" in capsys.readouterr().err


def test_raw_example_client(client, tmp_path):
    import subprocess

    _, service = client
    image = tmp_path / "q.png"
    cv2.imwrite(str(image), np.zeros((6, 8), np.uint8))
    out = subprocess.run(
        [sys.executable, str(ROOT / "clients/examples/raw_zenoh_client.py"), str(image),
         "--connect", f"tcp/127.0.0.1:{_port_of(service)}", "--map", MAP, "--camera-id", "cam0"],
        capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    assert "t = [1.0000 2.0000 3.0000]" in out.stdout
    assert service.requests[-1].image.format is P.ImageFormat.JPEG


def _port_of(service: FakeService) -> int:
    return service.port


def test_unreachable_endpoint_is_a_connection_error():
    with pytest.raises(ConnectionError, match="cannot open a Zenoh session"):
        RelocClient(f"tcp/127.0.0.1:{free_port()}", map=MAP)
