"""``reloc bench --only attack``: the attacks of docs/reliability.md as a suite (a benchmark, not
CI), each judged per attempt as *clean* or *broke something*.

Every case starts real ``reloc serve`` processes (a Zenoh peer on a free loopback port, multicast
scouting off, storage in a temporary folder), attacks them over real Zenoh sessions or on their
files on disk, and judges each attempt:

- **clean**: refused with the error code (or rejection event) the protocol names for it, or
  survived: nothing acknowledged lost, no content served that was not put, and the service still
  answers ``status`` afterwards;
- **broke**: an INTERNAL error, another code than the one named, no reply (a hang), a crash,
  an acknowledged keyframe lost, damaged or foreign content served.

Cases are registered explicitly in :data:`CASES` with their group (:data:`GROUPS`);
:func:`run_attack` runs them (all, or those named) and returns the JSON section;
:func:`table_lines` prints the table. Keyframes are tiny synthetic images (160x120 textured
noise), so the whole suite runs in a few minutes on a loaded two-core machine.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np
import numpy.typing as npt

from ...core.cameras import PinholeCamera
from .loopback import free_port, service_doc, toml_text

#: The map every attack service serves from its start.
MAP_NAME = "lab"
CAMERA_ID = "cam0"
METHOD = "sbi+p3p"
#: The groups of the issue's attack, in the table's order.
GROUPS = ("input", "storage", "quota", "replica")
#: Seconds a reply, an acknowledgement or a service start may take before it counts as a hang.
REPLY_TIMEOUT_S = 30.0
READY_TIMEOUT_S = 120.0


# -- verdicts ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Attempt:
    """One attempt of a case: clean (refused or survived as expected) or not, and why."""

    clean: bool
    detail: str


def clean(detail: str) -> Attempt:
    return Attempt(True, detail)


def broke(detail: str) -> Attempt:
    return Attempt(False, detail)


def judge_code(what: str, code: str | None, expected: Sequence[str]) -> Attempt:
    """An attempt refused with ``code`` (None: no refusal came): clean if it is one of
    ``expected``; INTERNAL, another code or none at all broke something."""
    if code is None:
        return broke(f"{what}: no refusal within {REPLY_TIMEOUT_S:.0f} s "
                     f"(expected {'/'.join(expected)})")
    if code in expected:
        return clean(f"{what}: {code}")
    return broke(f"{what}: {code} (expected {'/'.join(expected)})")


# -- the scene: tiny textured keyframes ---------------------------------------------------------

@dataclass(frozen=True)
class TinyScene:
    """A 160x120 pinhole camera and textured grey keyframes ((H, W) uint8) with their
    ``world_from_cam`` poses ((4, 4), a camera stepping 5 cm along x)."""

    camera: PinholeCamera
    images: tuple[npt.NDArray[np.uint8], ...]
    poses: tuple[npt.NDArray[np.float64], ...]

    def image(self, kf_id: int) -> npt.NDArray[np.uint8]:
        return self.images[kf_id % len(self.images)]

    def pose(self, kf_id: int) -> npt.NDArray[np.float64]:
        world_from_cam = self.poses[kf_id % len(self.poses)].copy()
        world_from_cam[0, 3] = 0.05 * kf_id
        return world_from_cam


def tiny_scene(n: int = 8, width: int = 160, height: int = 120, seed: int = 0) -> TinyScene:
    """``n`` keyframes of blurred noise at two scales (corners and blobs for the feature
    detectors), seeded."""
    rng = np.random.default_rng(seed)
    images = []
    for _ in range(n):
        coarse = cv2.resize(rng.uniform(0, 255, (height // 8, width // 8)), (width, height),
                            interpolation=cv2.INTER_CUBIC)
        fine = cv2.GaussianBlur(rng.uniform(0, 255, (height, width)), (0, 0), 1.0)
        images.append(np.clip(0.6 * coarse + 0.4 * fine, 0, 255).astype(np.uint8))
    camera = PinholeCamera(width=width, height=height, fx=0.8 * width, fy=0.8 * width,
                           cx=width / 2, cy=height / 2)
    return TinyScene(camera, tuple(images), tuple(np.eye(4) for _ in range(n)))


# -- a reloc serve process ------------------------------------------------------------------------

class AttackService:
    """``reloc serve`` on a free loopback port and the storage folder ``storage``, map
    :data:`MAP_NAME`, new maps allowed (the attack sends to new names), the code's default
    quotas unless ``quotas`` sets some (``[quotas]`` keys); started and stopped as a case
    needs. Its config and logs are kept in ``folder``."""

    def __init__(self, folder: Path, storage: Path | None = None, *,
                 snapshot_every: int = 0, quotas: Mapping[str, int] | None = None) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.storage = storage or folder / "storage"
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        doc = service_doc(self.endpoint, self.storage, [METHOD], {}, map_name=MAP_NAME,
                          workers=1, queue_size=8)
        doc["service"].update(allow_new_maps=True, train_on_load=False, fsync=True,
                              snapshot_every=snapshot_every,
                              instance=f"attack-{self.endpoint.rsplit(':', 1)[1]}")
        if quotas:
            doc["quotas"] = dict(quotas)
        self.config = folder / "service.toml"
        self.config.write_text(toml_text(doc))
        self.proc: subprocess.Popen[bytes] | None = None
        self.runs = 0

    @property
    def log_path(self) -> Path:
        return self.folder / f"service-{self.runs:02d}.log"

    def start(self) -> AttackService:
        """Start the process and wait until it answers ``status`` on :data:`MAP_NAME`."""
        from .loopback import wait_ready

        self.runs += 1
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(serve_command(self.config), stdout=log,
                                         stderr=subprocess.STDOUT)
        wait_ready(self.proc, self.endpoint, map_name=MAP_NAME, log=self.log_path,
                   timeout=READY_TIMEOUT_S)
        return self

    def stop(self, kind: str = "sigterm") -> int:
        """Stop by ``kill9`` or ``sigterm`` (kill -9 after 60 s); the exit code."""
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return -1 if proc is None else int(proc.returncode)
        proc.send_signal(signal.SIGKILL if kind == "kill9" else signal.SIGTERM)
        try:
            return proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()

    def restart(self, kind: str) -> int:
        code = self.stop(kind)
        self.start()
        return code

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def client(self, map_name: str = MAP_NAME) -> Any:
        """A :class:`RelocClient` on ``map_name`` of this service (close it after use)."""
        from reloc_client.client import RelocClient

        return RelocClient(self.endpoint, map=map_name, timeout=REPLY_TIMEOUT_S)

    def answers(self) -> str | None:
        """None if the process runs and answers ``status``, else what is wrong."""
        if self.proc is None or self.proc.poll() is not None:
            code = None if self.proc is None else self.proc.returncode
            return f"the service exited ({code}): {self.log_tail(300)}"
        try:
            with self.client() as c:
                c.status(timeout=REPLY_TIMEOUT_S)
        except Exception as exc:  # any failure to answer is the finding
            return f"status not answered: {type(exc).__name__}: {exc}"
        return None

    def log_tail(self, chars: int = 2000) -> str:
        path = self.log_path
        return path.read_text(errors="replace")[-chars:] if path.exists() else ""


def serve_command(config: Path) -> list[str]:
    return [sys.executable, "-m", "reloc_service.cli.main", "serve", "--config", str(config)]


@contextlib.contextmanager
def running(folder: Path, storage: Path | None = None, **kw: Any) -> Iterator[AttackService]:
    """An :class:`AttackService` started for the block and stopped (SIGTERM) after it."""
    service = AttackService(folder, storage, **kw)
    try:
        yield service.start()
    finally:
        service.stop("sigterm")


def put_acknowledged(client: Any, scene: TinyScene, ids: Sequence[int] | range) -> list[int]:
    """Put keyframes ``ids`` (camera :data:`CAMERA_ID` first) and wait for each to be
    journaled; the ids acknowledged (a refusal or a missing acknowledgement raises)."""
    client.set_camera(CAMERA_ID, scene.camera, wait=True)
    for kf_id in ids:
        client.add_keyframe(kf_id, scene.image(kf_id), scene.pose(kf_id), camera_id=CAMERA_ID,
                            wait=True)
    return list(ids)


def held_ids(client: Any, timeout: float = READY_TIMEOUT_S) -> set[int]:
    """The keyframe ids the client's map holds, once the map answers: after a start, maps
    are restored one by one after the first answers, and a fresh session learns the
    service's queryables a moment after it opens (NoReplyError until then), and a map whose
    journal still replays answers BUSY (its list is not whole yet); raised after ``timeout``
    seconds."""
    from reloc_client.client import NoReplyError, ServiceBusy

    deadline = time.monotonic() + timeout
    while True:
        try:
            return {info.id for info in client.keyframes(timeout=5.0)}
        except (NoReplyError, ServiceBusy):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def compare_held(what: str, held: set[int], expected: set[int]) -> Attempt:
    """Clean if exactly ``expected`` is held; else names what is lost and what is extra."""
    lost, extra = sorted(expected - held), sorted(held - expected)
    if not lost and not extra:
        return clean(f"{what}: all {len(expected)} held")
    return broke(f"{what}: lost {lost[:10]}{'...' if len(lost) > 10 else ''}, "
                 f"unexpected {extra[:10]}")


# -- raw Zenoh requests ------------------------------------------------------------------------

def query_code(session: Any, key: str, payload: bytes | None) -> str | None:
    """The error code of the reply to a get on ``key`` (``"OK"`` for a reply that is not an
    error, None for no reply within :data:`REPLY_TIMEOUT_S`)."""
    from reloc_client import protocol as wire

    replies = list(session.get(key, payload=payload, timeout=REPLY_TIMEOUT_S))
    if not replies:
        return None
    reply = replies[0]
    if reply.err is None:
        return "OK"
    return wire.ErrorReply.decode(reply.err.payload.to_bytes()).code.value


class EventLog:
    """Every event of every map (``reloc/*/events``) heard by ``session``."""

    def __init__(self, session: Any) -> None:
        from reloc_client import protocol as wire

        self.events: list[Any] = []
        self.cond = threading.Condition()

        def on_sample(sample: Any) -> None:
            with contextlib.suppress(Exception):  # a malformed event is not what is judged
                event = wire.Event.decode(sample.payload.to_bytes())
                with self.cond:
                    self.events.append(event)
                    self.cond.notify_all()

        self.sub = session.declare_subscriber("reloc/*/events", on_sample)

    def find(self, map_name: str, kind: str, **fields: Any) -> Any:
        with self.cond:
            for e in self.events:
                if e.map == map_name and e.kind.value == kind and all(
                        e.fields.get(k) == v for k, v in fields.items()):
                    return e
        return None

    def wait(self, map_name: str, kind: str, timeout: float = REPLY_TIMEOUT_S,
             **fields: Any) -> Any:
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                found = self.find(map_name, kind, **fields)
                if found is not None or time.monotonic() > deadline:
                    return found
                self.cond.wait(0.1)

    def close(self) -> None:
        self.sub.undeclare()


def put_block(session: Any, key: str, payload: bytes) -> None:
    """A put that waits under congestion (a put Zenoh dropped would not test the service)."""
    import zenoh

    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)


def heard_rejections(session: Any, log: EventLog, probe_map: str) -> bool:
    """Probe with garbage on ``probe_map`` until its rejection is heard: Zenoh routes a new
    subscriber asynchronously, and events published before it is known are not delivered."""
    from reloc_client import protocol as wire

    deadline = time.monotonic() + REPLY_TIMEOUT_S
    while time.monotonic() < deadline:
        put_block(session, wire.keys.keyframe("reloc", probe_map, 1), b"\xc1probe")
        if log.wait(probe_map, "keyframe_rejected", timeout=0.5) is not None:
            return True
    return False


# -- the registry --------------------------------------------------------------------------------

@dataclass
class Arena:
    """What a case gets: a folder of its own, the scene, and the shared input service (started
    on first use, stopped at the end of the run)."""

    folder: Path
    scene: TinyScene
    shared: dict[str, AttackService] = field(default_factory=dict)

    def input_service(self) -> AttackService:
        """One service for the input cases that need no restart of their own."""
        if "input" not in self.shared:
            service = AttackService(self.folder / "input-service")
            self.shared["input"] = service.start()
            with service.client() as c:
                put_acknowledged(c, self.scene, range(4))
        return self.shared["input"]

    def case_folder(self, name: str) -> Path:
        path = self.folder / name
        path.mkdir(parents=True, exist_ok=True)
        return path

    def close(self) -> None:
        for service in self.shared.values():
            service.stop("sigterm")
        self.shared.clear()


@dataclass(frozen=True)
class Case:
    """An attack case: its name, group, what it sends and what counts as clean."""

    name: str
    group: str
    summary: str
    run: Callable[[Arena], list[Attempt]]


CASES: dict[str, Case] = {}


def register(name: str, group: str, summary: str
             ) -> Callable[[Callable[[Arena], list[Attempt]]], Callable[[Arena], list[Attempt]]]:
    """Register ``fn(arena) -> [Attempt, ...]`` as case ``name`` of ``group``."""
    if group not in GROUPS:
        raise ValueError(f"attack case {name!r}: group {group!r}, expected one of {GROUPS}")

    def deco(fn: Callable[[Arena], list[Attempt]]) -> Callable[[Arena], list[Attempt]]:
        if name in CASES:
            raise ValueError(f"duplicate attack case {name!r}")
        CASES[name] = Case(name, group, summary, fn)
        return fn
    return deco


# -- input -------------------------------------------------------------------------------------

@register("garbage-new-maps", "input",
          "20 puts of garbage msgpack (keyframe and camera) to new map names: each rejected "
          "BAD_MSGPACK, no map served or written")
def garbage_new_maps(arena: Arena) -> list[Attempt]:
    from reloc_client import protocol as wire

    service = arena.input_service()
    names = [f"junk{i}" for i in range(20)]
    with service.client() as c:
        log = EventLog(c.session)
        try:
            if not heard_rejections(c.session, log, "junkprobe"):
                return [broke("no keyframe_rejected event for garbage on a new map name")]
            for i, name in enumerate(names):
                key = (wire.keys.camera("reloc", name, "c0") if i % 2
                       else wire.keys.keyframe("reloc", name, 1))
                put_block(c.session, key, b"\xc1garbage" * (i + 1))
            out = []
            served = {m for _, m in c.maps()}
            for i, name in enumerate(names):
                kind = "camera_rejected" if i % 2 else "keyframe_rejected"
                event = log.wait(name, kind)
                code = None if event is None else str(event.fields.get("code"))
                if name in served or any(p.name.startswith(name) for p in
                                         service.storage.iterdir()):
                    out.append(broke(f"{name}: a map was created by garbage"))
                else:
                    out.append(judge_code(f"{name} {kind}", code, ["BAD_MSGPACK"]))
            return out
        finally:
            log.close()


def nested(depth: int, *, maps: bool = False) -> bytes:
    """A msgpack value nested ``depth`` deep: one-element arrays (or one-key maps) around nil."""
    return (b"\x81\xa1a" if maps else b"\x91") * depth + b"\xc0"


def request_with(field_name: str, value: bytes, others: Mapping[str, Any] | None = None
                 ) -> bytes:
    """A msgpack request map ``{"v": 1, **others, field_name: <value>}`` with ``value`` already
    encoded (so that only ``field_name`` is wrong)."""
    fields = {"v": 1, **(others or {})}
    fields.pop(field_name, None)
    head = b"\xde" + (len(fields) + 1).to_bytes(2, "big")   # map 16: any field count
    body = b"".join(msgpack.packb(k) + msgpack.packb(v, use_bin_type=True)
                    for k, v in fields.items())
    return head + body + msgpack.packb(field_name) + value


def deep_requests(arena: Arena, depths: Sequence[int]) -> list[Attempt]:
    """``relocalize.image``, ``train.method`` and a keyframe put's ``image`` nested ``depths``
    deep (arrays and maps), every other field valid: each refused with a named code, never
    INTERNAL."""
    from reloc_client import protocol as wire
    from reloc_client.client import keyframe_put_bytes, to_wire_image

    expected = [c.value for c in wire.ErrorCode if c is not wire.ErrorCode.INTERNAL]
    scene = arena.scene
    query = msgpack.unpackb(wire.RelocalizeRequest(
        image=to_wire_image(scene.image(0)), camera_id=CAMERA_ID).encode())
    put = msgpack.unpackb(keyframe_put_bytes(0, scene.image(0), scene.pose(0),
                                             camera_id=CAMERA_ID))
    service = arena.input_service()
    out = []
    with service.client() as c:
        for depth in depths:
            for maps in (False, True):
                shape = "maps" if maps else "arrays"
                for key, name, others in (
                        (wire.keys.relocalize("reloc", MAP_NAME), "relocalize.image", query),
                        (wire.keys.train("reloc", MAP_NAME), "train.method", {})):
                    raw = request_with(name.split(".")[1], nested(depth, maps=maps), others)
                    code = query_code(c.session, key, raw)
                    out.append(judge_code(f"{name} {shape} {depth} deep", code, expected))
        log = EventLog(c.session)
        try:
            heard_rejections(c.session, log, "deepprobe")
            for n, depth in enumerate(depths):
                kf_id = 900 + n
                put_block(c.session, wire.keys.keyframe("reloc", MAP_NAME, kf_id),
                          request_with("image", nested(depth), {**put, "id": kf_id}))
                event = log.wait(MAP_NAME, "keyframe_rejected", id=kf_id)
                code = None if event is None else str(event.fields.get("code"))
                out.append(judge_code(f"keyframe.image arrays {depth} deep", code, expected))
        finally:
            log.close()
    return out


@register("msgpack-nested-1e5", "input",
          "relocalize.image, train.method and a keyframe's image nested 100,000 deep (arrays, "
          "maps): a named error code, not INTERNAL")
def msgpack_nested_1e5(arena: Arena) -> list[Attempt]:
    return deep_requests(arena, [100_000])


@register("arrays-1000-deep", "input",
          "relocalize.image, train.method and a keyframe's image nested 500 and 1,000 deep "
          "(within msgpack's own limit): a named error code, not INTERNAL")
def arrays_1000_deep(arena: Arena) -> list[Attempt]:
    return deep_requests(arena, [500, 1000])


def flat_image(width: int, height: int, ext: str) -> bytes:
    """A flat grey image encoded as ``ext``: few bytes that declare ``width`` x ``height``."""
    ok, buf = cv2.imencode(ext, np.full((height, width), 128, np.uint8))
    assert ok
    return buf.tobytes()


@register("image-bomb", "input",
          "relocalize with a PNG / JPEG of a few KB declaring 4096x4096 and an inline 4096x4096 "
          "camera: IMAGE_TOO_LARGE, service memory barely rises")
def image_bomb(arena: Arena) -> list[Attempt]:
    from reloc_client import protocol as wire
    from reloc_client.client import ServiceError

    service = arena.input_service()
    big = PinholeCamera(width=4096, height=4096, fx=3000.0, fy=3000.0, cx=2048.0, cy=2048.0)
    out = []
    with service.client() as c:
        for ext in (".png", ".jpg"):
            data = flat_image(4096, 4096, ext)
            before = peak_rss_reset(service.pid)
            try:
                c.relocalize(wire.WireImage.from_bytes(data), camera=big)
                code: str | None = "OK"
            except ServiceError as exc:
                code = exc.code.value
            except TimeoutError:
                code = None
            rise = peak_rss_mb(service.pid) - before
            attempt = judge_code(f"{ext[1:]} of {len(data) // 1024} KB declaring 4096x4096",
                                 code, ["IMAGE_TOO_LARGE"])
            if rise > 300:
                attempt = broke(f"{attempt.detail}, but peak memory +{rise:.0f} MB")
            out.append(Attempt(attempt.clean, f"{attempt.detail} (peak +{rise:.0f} MB)"))
    return out


def peak_rss_reset(pid: int) -> float:
    """Reset process ``pid``'s peak resident memory; its resident memory now, in MB."""
    with contextlib.suppress(OSError):
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    return _status_mb(pid, "VmRSS")


def peak_rss_mb(pid: int) -> float:
    return _status_mb(pid, "VmHWM")


def _status_mb(pid: int, key: str) -> float:
    with contextlib.suppress(OSError, ValueError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


@register("oversized-put", "input",
          "a keyframe put and a relocalize query one byte above the payload limit: "
          "PAYLOAD_TOO_LARGE")
def oversized_put(arena: Arena) -> list[Attempt]:
    from reloc_client import protocol as wire

    service = arena.input_service()
    too_big = b"\x00" * (wire.DEFAULT_LIMITS.max_payload_bytes + 1)
    with service.client() as c:
        log = EventLog(c.session)
        try:
            heard_rejections(c.session, log, "bigprobe")
            put_block(c.session, wire.keys.keyframe("reloc", MAP_NAME, 77), too_big)
            event = log.wait(MAP_NAME, "keyframe_rejected", id=77)
            put_code = None if event is None else str(event.fields.get("code"))
        finally:
            log.close()
        get_code = query_code(c.session, wire.keys.relocalize("reloc", MAP_NAME), too_big)
    return [judge_code(f"put of {len(too_big)} bytes", put_code, ["PAYLOAD_TOO_LARGE"]),
            judge_code(f"relocalize of {len(too_big)} bytes", get_code, ["PAYLOAD_TOO_LARGE"])]


@register("get-everything", "input",
          "get reloc/** (an empty payload to every queryable): no INTERNAL, no training "
          "started, every reply an answer or a named refusal")
def get_everything(arena: Arena) -> list[Attempt]:
    import zenoh
    from reloc_client import protocol as wire

    service = arena.input_service()
    with service.client() as c:
        replies = list(c.session.get("reloc/**", timeout=REPLY_TIMEOUT_S,
                                     consolidation=zenoh.ConsolidationMode.NONE))
        codes = [wire.ErrorReply.decode(r.err.payload.to_bytes()).code.value
                 for r in replies if r.err is not None]
        training = c.status().training
    detail = (f"{len(replies)} replies, {len(codes)} refusals "
              f"({', '.join(sorted(set(codes))) or 'none'})")
    if not replies:
        return [broke("get reloc/**: no reply at all")]
    if "INTERNAL" in codes:
        return [broke(f"get reloc/**: INTERNAL among {detail}")]
    if training:
        return [broke(f"get reloc/**: an empty get started training; {detail}")]
    return [clean(f"get reloc/**: {detail}")]


#: Names the protocol accepts whose percent-encoded form is beyond NAME_MAX (255 bytes).
LONG_NAMES = {"30 Hangul": "\ud55c" * 30, "64 emoji": "\U0001f681" * 64, "128 '%'": "%" * 128}


@register("long-map-names", "input",
          "maps named with 30 Hangul, 64 emoji or 128 '%' characters: created by their first "
          "put and restored with their keyframes after a restart")
def long_map_names(arena: Arena) -> list[Attempt]:
    from reloc_client.client import ServiceError

    service = AttackService(arena.case_folder("long-map-names"))
    service.start()
    out: dict[str, Attempt] = {}
    try:
        for label, name in LONG_NAMES.items():
            try:
                with service.client(name) as c:
                    put_acknowledged(c, arena.scene, range(2))
            except (ServiceError, TimeoutError) as exc:
                out[label] = broke(f"{label}: put refused: {exc}")
        service.restart("sigterm")
        for label, name in LONG_NAMES.items():
            if label in out:
                continue
            try:
                with service.client(name) as c:
                    out[label] = compare_held(f"{label} after a restart",
                                              held_ids(c), {0, 1})
            except (ServiceError, TimeoutError) as exc:
                out[label] = broke(f"{label} after a restart: {exc}")
    finally:
        service.stop("sigterm")
    return list(out.values())


# -- storage -----------------------------------------------------------------------------------

@register("second-service", "storage",
          "a second reloc serve on the same storage while the first serves: refused (exit != 0) "
          "naming the holder's pid, nothing written; the first keeps every acknowledged "
          "keyframe, also after its restart")
def second_service(arena: Arena) -> list[Attempt]:
    folder = arena.case_folder("second-service")
    first = AttackService(folder / "first").start()
    try:
        with first.client() as c:
            acked = put_acknowledged(c, arena.scene, range(10))
        before = files_of(first.storage)
        second = AttackService(folder / "second", first.storage)
        with open(folder / "second.log", "wb") as log:
            proc = subprocess.run(serve_command(second.config), stdout=log,
                                  stderr=subprocess.STDOUT, timeout=READY_TIMEOUT_S)
        said = (folder / "second.log").read_text(errors="replace").strip()
        refused = (proc.returncode != 0 and f"pid {first.pid}" in said
                   and files_of(first.storage) == before)
        with first.client() as c:
            acked += put_acknowledged(c, arena.scene, range(10, 20))
        first.restart("sigterm")
        with first.client() as c:
            kept = compare_held("the first service after a restart", held_ids(c), set(acked))
    finally:
        first.stop("sigterm")
    verdict = (clean if refused and kept.clean else broke)(
        f"second service exit {proc.returncode}: {said.splitlines()[-1][:120] if said else ''}; "
        f"{kept.detail}")
    return [verdict]


def files_of(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` (lock holder records too) by relative path."""
    return {p.relative_to(directory).as_posix(): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


@register("kill9-restart", "storage",
          "kill -9 right after the last acknowledgement, three times (no snapshots: the "
          "journal alone): every acknowledged keyframe is back after each restart")
def kill9_restart(arena: Arena) -> list[Attempt]:
    service = AttackService(arena.case_folder("kill9-restart")).start()
    acked: list[int] = []
    out = []
    try:
        for n in range(3):
            with service.client() as c:
                acked += put_acknowledged(c, arena.scene, range(6 * n, 6 * n + 6))
            attempt = kill9_and_compare(service, acked)
            out.append(attempt)
            if not attempt.clean:
                break
    finally:
        service.stop("sigterm")
    return out


def kill9_and_compare(service: AttackService, acked: Sequence[int]) -> Attempt:
    """kill -9 the service, start it again: clean if it holds exactly ``acked``."""
    what = f"kill -9 after {len(acked)} acknowledged"
    try:
        code = service.restart("kill9")
    except Exception as exc:  # the restart itself failed: what the attack found
        return broke(f"{what}, restart failed: {type(exc).__name__}: {exc}")
    with service.client() as c:
        return compare_held(f"{what} (exit {code})", held_ids(c), set(acked))


#: Journal records between snapshots in the mid-snapshot case: the 9th record (a camera and 8
#: keyframes) starts one, and the kill -9 follows the 8th keyframe's acknowledgement.
SNAPSHOT_EVERY = 8


@register("kill9-mid-snapshot", "storage",
          "kill -9 while a snapshot is being written (its directory without a manifest yet), "
          "the map's first and a later one: every acknowledged keyframe is back after the "
          "restart")
def kill9_mid_snapshot(arena: Arena) -> list[Attempt]:
    out = []
    for later in (False, True):
        folder = arena.case_folder(f"kill9-mid-snapshot-{'later' if later else 'first'}")
        service = AttackService(folder, snapshot_every=SNAPSHOT_EVERY).start()
        try:
            acked: list[int] = []
            if later:  # a first snapshot, complete: SIGTERM writes one before it exits
                with service.client() as c:
                    acked += put_acknowledged(c, arena.scene, range(100, 104))
                service.restart("sigterm")
            with service.client() as c:
                acked += put_acknowledged(c, arena.scene, range(SNAPSHOT_EVERY))
            partial = wait_partial_snapshot(service.storage / MAP_NAME)
            attempt = kill9_and_compare(service, acked)
            label = "a later snapshot" if later else "the first snapshot"
            out.append(Attempt(attempt.clean, f"{label} ({partial} incomplete at the kill): "
                                              f"{attempt.detail}"))
        finally:
            service.stop("sigterm")
    return out


def wait_partial_snapshot(map_dir: Path, timeout: float = 10.0) -> int:
    """Wait (polling every 5 ms) until a snapshot of ``map_dir`` is being written, so that a
    kill lands in the middle of it; the incomplete snapshots then (0 after ``timeout``)."""
    deadline = time.monotonic() + timeout
    while True:
        partial = partial_snapshots(map_dir)
        if partial or time.monotonic() > deadline:
            return partial
        time.sleep(0.005)


def partial_snapshots(map_dir: Path) -> int:
    """Snapshot directories of ``map_dir`` without their manifest (being written)."""
    snapshots = map_dir / "map" / "snapshots"
    if not snapshots.is_dir():
        return 0
    return sum(not (d / "manifest.json").exists() for d in snapshots.iterdir() if d.is_dir())


JOURNAL_IDS = range(6)


def journaled_storage(arena: Arena) -> Path:
    """A storage whose map holds camera cam0 and keyframes 0-5 in its journal only (no
    snapshot: the service was killed -9 after the acknowledgements); made once, copied by
    each attempt."""
    template = arena.folder / "journal-template"
    if not template.exists():
        service = AttackService(arena.folder / "journal-template-service", template).start()
        try:
            with service.client() as c:
                put_acknowledged(c, arena.scene, JOURNAL_IDS)
        finally:
            service.stop("kill9")
    return template


def journal_records(map_dir: Path) -> tuple[Path, bytes, list[tuple[int, int, int | None]]]:
    """The map's first journal segment, its bytes, and (payload offset, payload length,
    keyframe id or None) of each of its records."""
    from ...storage.journal import scan_segment

    [segment] = sorted((map_dir / "journal").glob("*.journal"))[:1]
    data = segment.read_bytes()
    rows, pos = [], 0
    for record in scan_segment(segment).records:
        offset = data.index(record, pos)
        op = msgpack.unpackb(record)
        rows.append((offset, len(record), op.get("id") if op.get("op") == "kf" else None))
        pos = offset + len(record)
    return segment, data, rows


#: The status counters that report damaged journal bytes (skipped or a torn tail).
DAMAGE_COUNTERS = ("restore_journal_skipped", "restore_journal_torn_bytes")


def restore_damaged(arena: Arena, name: str, damage: Callable[[Path], int | list[int]]
                    ) -> Attempt:
    """Copy the journaled storage, ``damage`` its map's journal (returns the keyframe ids it
    destroyed), start a service on it: clean if exactly those are missing and the map's status
    counters report the damage (:data:`DAMAGE_COUNTERS`)."""
    folder = arena.case_folder(name)
    storage = folder / "storage"
    shutil.copytree(journaled_storage(arena), storage)
    lost = damage(storage / MAP_NAME)
    lost = lost if isinstance(lost, list) else [lost]
    with running(folder, storage) as service, service.client() as c:
        held = held_ids(c)
        counters = c.status().counters
    verdict = compare_held(f"keyframe(s) {lost} destroyed, the rest", held, set(JOURNAL_IDS) - set(lost))
    reported = ", ".join(f"{k} = {counters.get(k, 0)}" for k in DAMAGE_COUNTERS)
    if verdict.clean and not any(counters.get(k) for k in DAMAGE_COUNTERS):
        return broke(f"{verdict.detail}, but not reported ({reported})")
    return Attempt(verdict.clean, f"{verdict.detail}; {reported}")


def flip_byte(segment: Path, offset: int) -> None:
    data = bytearray(segment.read_bytes())
    data[offset] ^= 0x10
    segment.write_bytes(bytes(data))


@register("journal-bit-flip", "storage",
          "one bit flipped in a mid-journal record's payload, then in another's length field: "
          "exactly that keyframe lost (of 6), the skip counted in status")
def journal_bit_flip(arena: Arena) -> list[Attempt]:
    from ...storage.journal import SYNC

    def in_payload(map_dir: Path) -> int:
        segment, _, rows = journal_records(map_dir)
        offset, size, kf_id = rows[3]
        flip_byte(segment, offset + size - 1)
        return int(kf_id)  # type: ignore[arg-type]

    def in_length(map_dir: Path) -> int:
        segment, data, rows = journal_records(map_dir)
        offset, _, kf_id = rows[4]
        frame = data.rindex(SYNC, 0, offset)
        flip_byte(segment, frame + len(SYNC) + 1)   # the second byte of the length field
        return int(kf_id)  # type: ignore[arg-type]

    return [restore_damaged(arena, "bit-flip-payload", in_payload),
            restore_damaged(arena, "bit-flip-length", in_length)]


@register("journal-zeroed-tail", "storage",
          "the journal's last record zeroed, then the last two: exactly those keyframes lost, "
          "the damaged bytes counted in status")
def journal_zeroed_tail(arena: Arena) -> list[Attempt]:
    from ...storage.journal import SYNC

    def zero_last(count: int) -> Callable[[Path], list[int]]:
        def damage(map_dir: Path) -> list[int]:
            segment, data, rows = journal_records(map_dir)
            first = data.rindex(SYNC, 0, rows[-count][0])
            segment.write_bytes(data[:first] + bytes(len(data) - first))
            return [int(r[2]) for r in rows[-count:] if r[2] is not None]
        return damage

    return [restore_damaged(arena, f"zeroed-tail-{n}", zero_last(n)) for n in (1, 2)]


@register("concurrent-delete-put-train", "storage",
          "deletes, puts and training of one map at once, then kill -9 and SIGTERM restarts: "
          "exactly the acknowledged changes held, training ends or is refused by name")
def concurrent_delete_put_train(arena: Arena) -> list[Attempt]:
    service = AttackService(arena.case_folder("concurrent"), snapshot_every=6).start()
    out = []
    try:
        with service.client() as c:
            put_acknowledged(c, arena.scene, range(10))
        expected = set(range(10))
        for n, kind in enumerate(("kill9", "sigterm")):
            base = 100 * (n + 1)
            problems, expected = concurrent_round(service, arena.scene, expected, base)
            with service.client() as c:
                live = compare_held("while serving", held_ids(c), expected)
            code = service.restart(kind)
            with service.client() as c:
                after = compare_held(f"after {kind} (exit {code})", held_ids(c), expected)
            ok = not problems and live.clean and after.clean
            out.append(Attempt(ok, "; ".join([*problems, live.detail, after.detail])))
    finally:
        service.stop("sigterm")
    return out


def concurrent_round(service: AttackService, scene: TinyScene, held: set[int], base: int
                     ) -> tuple[list[str], set[int]]:
    """Delete half of ``held``, put 8 new keyframes from ``base`` and train twice, in three
    threads; the problems seen and the ids that must now be held."""
    from reloc_client.client import ServiceError

    doomed = sorted(held)[: len(held) // 2]
    new = list(range(base, base + 8))
    problems: list[str] = []

    def deleter() -> None:
        with service.client() as c:
            for kf_id in doomed:
                c.remove_keyframe(kf_id, wait=True)

    def putter() -> None:
        with service.client() as c:
            put_acknowledged(c, scene, new)

    def trainer() -> None:
        with service.client() as c:
            for _ in range(2):
                try:
                    c.train(wait=True, timeout=120)
                except ServiceError as exc:   # a named refusal (e.g. BUSY) is an answer
                    if exc.code.value == "INTERNAL":
                        raise

    def guarded(fn: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            try:
                fn()
            except Exception as exc:  # each thread's failure is a finding of the round
                problems.append(f"{fn.__name__}: {type(exc).__name__}: {exc}")
        return run

    threads = [threading.Thread(target=guarded(f)) for f in (deleter, putter, trainer)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    problems += [f"{t.name} hangs" for t in threads if t.is_alive()]
    return problems, (held - set(doomed)) | set(new)


# -- quota ---------------------------------------------------------------------------------------
# Each quota ([quotas] of the service configuration) set low on a service of its own.

def put_code(client: Any, scene: TinyScene, kf_id: int) -> str | None:
    """Put keyframe ``kf_id`` and wait: ``"OK"`` once journaled, the refusal's error code, or
    None when neither came within :data:`REPLY_TIMEOUT_S`."""
    from reloc_client.client import NoReplyError, ServiceError

    try:
        client.add_keyframe(kf_id, scene.image(kf_id), scene.pose(kf_id), camera_id=CAMERA_ID,
                            wait=True)
    except ServiceError as exc:
        return exc.code.value
    except NoReplyError:
        return None
    return "OK"


def put_new_map_code(service: AttackService, scene: TinyScene, name: str) -> str | None:
    """The first put to map ``name`` (camera inline, so it may create the map)."""
    from reloc_client.client import NoReplyError, ServiceError

    with service.client(name) as c:
        try:
            c.add_keyframe(0, scene.image(0), scene.pose(0), camera=scene.camera, wait=True)
        except ServiceError as exc:
            return exc.code.value
        except NoReplyError:
            return None
    return "OK"


@register("quota-maps", "quota",
          "max_maps = 2 (lab and one more): a put creating a second map is acknowledged, "
          "puts creating a third, fourth and fifth are refused QUOTA_EXCEEDED and create "
          "nothing, also after a restart")
def quota_maps(arena: Arena) -> list[Attempt]:
    service = AttackService(arena.case_folder("quota-maps"), quotas={"max_maps": 2}).start()
    out = []
    try:
        out.append(judge_code("a put creating map 'second'",
                              put_new_map_code(service, arena.scene, "second"), ["OK"]))
        for name in ("third", "fourth", "fifth"):
            attempt = judge_code(f"a put creating map {name!r}",
                                 put_new_map_code(service, arena.scene, name),
                                 ["QUOTA_EXCEEDED"])
            if (service.storage / name).exists():
                attempt = broke(f"{attempt.detail}, yet {name!r} was written to the storage")
            out.append(attempt)
        service.restart("sigterm")
        with service.client("second") as c:
            kept = compare_held("'second' after a restart", held_ids(c), {0})
        again = judge_code("after a restart, a put creating 'sixth'",
                           put_new_map_code(service, arena.scene, "sixth"), ["QUOTA_EXCEEDED"])
        out.append(Attempt(kept.clean and again.clean, f"{kept.detail}; {again.detail}"))
    finally:
        service.stop("sigterm")
    return out


@register("quota-keyframes", "quota",
          "max_keyframes_per_map = 4: three puts beyond refused QUOTA_EXCEEDED; a replacement "
          "is not one more; a delete frees one; after kill -9 the count is the same")
def quota_keyframes(arena: Arena) -> list[Attempt]:
    scene = arena.scene
    service = AttackService(arena.case_folder("quota-keyframes"),
                            quotas={"max_keyframes_per_map": 4}).start()
    out = []
    try:
        with service.client() as c:
            put_acknowledged(c, scene, range(4))
            for kf_id in (4, 5, 6):
                out.append(judge_code(f"keyframe {kf_id} beyond the 4 allowed", put_code(c, scene, kf_id),
                                      ["QUOTA_EXCEEDED"]))
            out.append(judge_code("keyframe 0 replaced", put_code(c, scene, 0), ["OK"]))
            c.remove_keyframe(1, wait=True)
            out.append(judge_code("keyframe 4 after deleting 1", put_code(c, scene, 4), ["OK"]))
        service.restart("kill9")
        with service.client() as c:
            kept = compare_held("after kill -9", held_ids(c), {0, 2, 3, 4})
            again = judge_code("keyframe 5 after it", put_code(c, scene, 5), ["QUOTA_EXCEEDED"])
        out.append(Attempt(kept.clean and again.clean, f"{kept.detail}; {again.detail}"))
    finally:
        service.stop("sigterm")
    return out


#: The byte quota of the quota-bytes case: a few of the tiny keyframes.
MAP_BYTES = 150_000


@register("quota-bytes", "quota",
          f"max_map_bytes = {MAP_BYTES}: keyframes put until one is refused QUOTA_EXCEEDED "
          "(the count within the limit), then after kill -9 every acknowledged one held and "
          "the next still refused")
def quota_bytes(arena: Arena) -> list[Attempt]:
    scene = arena.scene
    service = AttackService(arena.case_folder("quota-bytes"),
                            quotas={"max_map_bytes": MAP_BYTES}).start()
    acked: list[int] = []
    code: str | None = "OK"
    try:
        with service.client() as c:
            c.set_camera(CAMERA_ID, scene.camera, wait=True)
            while code == "OK" and len(acked) < 30:
                code = put_code(c, scene, len(acked))
                if code == "OK":
                    acked.append(len(acked))
            counted = c.status().counters.get("quota_bytes")
        refused = judge_code(f"keyframe {len(acked)} after {len(acked)} acknowledged "
                             f"({counted} bytes counted)", code, ["QUOTA_EXCEEDED"])
        if refused.clean and not (isinstance(counted, int) and counted <= MAP_BYTES):
            refused = broke(f"{refused.detail}, but {counted} bytes counted: over the limit")
        service.restart("kill9")
        with service.client() as c:
            kept = compare_held("after kill -9", held_ids(c), set(acked))
            again = judge_code("the next put", put_code(c, scene, len(acked)),
                               ["QUOTA_EXCEEDED"])
    finally:
        service.stop("sigterm")
    return [refused, Attempt(kept.clean and again.clean, f"{kept.detail}; {again.detail}")]


# -- restore completeness --------------------------------------------------------------------------
# Storage whose snapshots disagree with the journal or with the map: the map is served as
# degraded naming what it lacks, or refused by name; never another map's content. Cases still
# to add here: a deleted or emptied journal segment.

def two_snapshot_storage(arena: Arena, name: str) -> tuple[AttackService, Path]:
    """A stopped service whose map ``lab`` has snapshot A (keyframes 0-3) and, after it,
    snapshot B (keyframes 0-7; each written by a SIGTERM), and map ``other`` (keyframes
    20-21) in a snapshot."""
    service = AttackService(arena.case_folder(name)).start()
    try:
        with service.client() as c:
            put_acknowledged(c, arena.scene, range(4))
        with service.client("other") as c:
            put_acknowledged(c, arena.scene, range(20, 22))
        service.restart("sigterm")
        with service.client() as c:
            put_acknowledged(c, arena.scene, range(4, 8))
    finally:
        service.stop("sigterm")
    return service, service.storage


def map_directory(storage: Path, name: str) -> Path:
    from ...service.durability import map_dirname

    return storage / map_dirname(name)


@register("another-maps-snapshot", "storage",
          "another map's map/ directory (its snapshots) swapped into lab's: lab refused by "
          "name (STORAGE_ERROR), never served with the other map's keyframes; the other map "
          "still served")
def another_maps_snapshot(arena: Arena) -> list[Attempt]:
    from reloc_client.client import ServiceError

    service, storage = two_snapshot_storage(arena, "another-maps-snapshot")
    lab, other = map_directory(storage, MAP_NAME), map_directory(storage, "other")
    shutil.rmtree(lab / "map")
    shutil.copytree(other / "map", lab / "map")
    try:
        try:
            service.start()
            return [broke("lab answered status with another map's snapshot in place")]
        except ServiceError as exc:
            refusal = judge_code(f"lab: {exc.message[:100]}", exc.code.value,
                                 ["STORAGE_ERROR"])
        with service.client("other") as c:
            kept = compare_held("'other'", held_ids(c), {20, 21})
        return [Attempt(refusal.clean and kept.clean, f"{refusal.detail}; {kept.detail}")]
    finally:
        service.stop("sigterm")


@register("current-rolled-back", "storage",
          "map/CURRENT pointed back at the kept previous snapshot: lab served degraded, "
          "naming the keyframes the newer snapshot held (4-7) as missing")
def current_rolled_back(arena: Arena) -> list[Attempt]:
    service, storage = two_snapshot_storage(arena, "current-rolled-back")
    snapshots = map_directory(storage, MAP_NAME) / "map"
    current = (snapshots / "CURRENT").read_text().strip()
    older = sorted(p.name for p in (snapshots / "snapshots").iterdir()
                   if f"snapshots/{p.name}" != current)
    if not older:
        return [broke(f"no previous snapshot kept beside {current} (the case needs one)")]
    (snapshots / "CURRENT").write_text(f"snapshots/{older[-1]}\n")
    try:
        service.start()
        with service.client() as c:
            held = held_ids(c)
            status = c.status()
    finally:
        service.stop("sigterm")
    what = f"CURRENT {current} -> snapshots/{older[-1]}"
    missing = status.counters.get("restore_missing_keyframes")
    if held - set(range(8)):
        return [broke(f"{what}: served keyframes never put: {sorted(held - set(range(8)))}")]
    if not status.degraded or missing != len(set(range(8)) - held):
        return [broke(f"{what}: held {sorted(held)}, degraded {status.degraded!r}, "
                      f"restore_missing_keyframes = {missing}")]
    return [clean(f"{what}: held {sorted(held)}, degraded: {status.degraded[:90]}")]


# -- replica -------------------------------------------------------------------------------------
# Cases of replicas (a peer serving another map under the same name, one replica's disk full,
# a lagging replica) are registered here, in group "replica", once replicas compare map
# identities and acknowledge per replica.


# -- the run -------------------------------------------------------------------------------------

def run_case(case: Case, arena: Arena) -> dict[str, Any]:
    """Run ``case``; then the shared service must still answer. A case that raises broke
    something (its exception is the detail)."""
    start = time.perf_counter()
    try:
        attempts = case.run(arena)
    except Exception as exc:  # an attack the harness could not finish is reported, not hidden
        traceback.print_exc()
        attempts = [broke(f"{type(exc).__name__}: {exc}")]
    if case.group == "input" and "input" in arena.shared:
        problem = arena.shared["input"].answers()
        if problem is not None:
            attempts.append(broke(f"after the case: {problem}"))
    n_clean = sum(a.clean for a in attempts)
    return {"case": case.name, "group": case.group, "summary": case.summary,
            "attempts": len(attempts), "clean": n_clean, "broke": len(attempts) - n_clean,
            "details": [{"clean": a.clean, "detail": a.detail} for a in attempts],
            "seconds": time.perf_counter() - start}


def run_attack(names: Sequence[str] | None = None, *, workdir: Path | None = None,
               on_progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the cases ``names`` (default: all of :data:`CASES`, in order); the JSON section:
    one row per case and the totals."""
    unknown = sorted(set(names or ()) - set(CASES))
    if unknown:
        raise ValueError(f"unknown attack case(s) {unknown}; expected some of {list(CASES)}")
    say = on_progress or (lambda _m: None)
    started = time.perf_counter()
    with contextlib.ExitStack() as stack:
        folder = workdir or Path(stack.enter_context(
            tempfile.TemporaryDirectory(prefix="reloc-attack-")))
        folder.mkdir(parents=True, exist_ok=True)
        arena = Arena(folder, tiny_scene())
        stack.callback(arena.close)
        rows = []
        for name in names or list(CASES):
            row = run_case(CASES[name], arena)
            rows.append(row)
            say(f"attack {name}: {row['attempts']} attempts, {row['clean']} clean, "
                f"{row['broke']} broke ({row['seconds']:.1f} s)")
    totals = {k: sum(r[k] for r in rows) for k in ("attempts", "clean", "broke")}
    return {"cases": rows, **totals, "seconds": time.perf_counter() - started,
            "groups": {g: [c.name for c in CASES.values() if c.group == g] for g in GROUPS}}


def table_lines(attack: Mapping[str, Any]) -> list[str]:
    """The attack's result as a Markdown table (a case per row; the first attempt that broke
    something, else the first attempt's detail) and the totals."""
    rows = ["| case | group | attempts | clean | broke | detail |", "|---|---|---|---|---|---|"]
    for r in attack["cases"]:
        details = r["details"]
        shown = next((d for d in details if not d["clean"]), details[0] if details else None)
        text = "" if shown is None else shorten(shown["detail"]).replace("|", "\\|")
        rows.append(f"| {r['case']} | {r['group']} | {r['attempts']} | {r['clean']} | "
                    f"{r['broke']} | {text} |")
    return [*rows, "", f"attempts / clean / broke something: {attack['attempts']} / "
                       f"{attack['clean']} / {attack['broke']}", ""]


def shorten(text: str, limit: int = 200) -> str:
    """``text`` cut to ``limit`` characters for a table cell (the JSON keeps it whole)."""
    return text if len(text) <= limit else text[:limit - 3] + "..."


def run_into(result: dict[str, Any], workdir: Path | None, say: Callable[[str], None]) -> None:
    """Run every case into ``result["attack"]`` (an ``{"error": ...}`` if the run failed)."""
    from .samples import json_safe

    try:
        result["attack"] = json_safe(run_attack(workdir=workdir and workdir / "attack",
                                                on_progress=say))
    except Exception as exc:  # the error is the section's result, as for the others
        traceback.print_exc()
        result["attack"] = {"error": f"{type(exc).__name__}: {exc}"}
        return
    result.setdefault("section_seconds", {})["attack"] = result["attack"]["seconds"]


if __name__ == "__main__":  # one case by name, for a quick look: python -m ... attack NAME
    print(json.dumps(run_attack(sys.argv[1:] or None, on_progress=print), indent=1))
