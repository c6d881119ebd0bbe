"""What every attack case shares: verdicts, the tiny scene, ``reloc serve`` processes, raw
Zenoh requests and the registry of cases."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ....core.cameras import PinholeCamera
from ..loopback import free_port, service_doc, toml_text

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
                 snapshot_every: int = 0, quotas: Mapping[str, int] | None = None,
                 connect: Sequence[str] = (), service: Mapping[str, Any] | None = None
                 ) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.storage = storage or folder / "storage"
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        doc = service_doc(self.endpoint, self.storage, [METHOD], {}, map_name=MAP_NAME,
                          workers=1, queue_size=8)
        doc["service"].update(allow_new_maps=True, train_on_load=False, fsync=True,
                              snapshot_every=snapshot_every,
                              instance=f"attack-{self.endpoint.rsplit(':', 1)[1]}")
        doc["service"].update(service or {})
        doc["zenoh"]["connect"] = list(connect)
        if quotas:
            doc["quotas"] = dict(quotas)
        self.instance: str = doc["service"]["instance"]
        self.config = folder / "service.toml"
        self.config.write_text(toml_text(doc))
        self.proc: subprocess.Popen[bytes] | None = None
        self.runs = 0

    @property
    def log_path(self) -> Path:
        return self.folder / f"service-{self.runs:02d}.log"

    def start(self) -> AttackService:
        """Start the process and wait until it answers ``status`` on :data:`MAP_NAME`."""
        from ..loopback import wait_ready

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


