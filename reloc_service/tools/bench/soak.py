"""``reloc bench --only soak``: the reliability soak run of docs/reliability.md (a benchmark,
not CI).

A ``reloc serve`` child process with storage in a temporary folder serves one map built from a
synthetic scene, while, for ``SoakConf.seconds``:

- ``query_clients`` clients query ``relocalize`` back to back (JPEG queries);
- one client streams keyframes (new ids, in order, each waited for until acknowledged or
  ``ack_timeout_s``), one deletes the oldest acknowledged streamed keyframes so that about
  ``keep_streamed`` of them stay in the map;
- a subscriber records every ``keyframe_added`` / ``keyframe_removed`` event: those are the
  acknowledgements (the service publishes them after the change is journaled);
- every ``restart_every_s`` the service is stopped, by ``kill -9`` and SIGTERM in turn, and
  started again on the same storage; its resident memory is sampled every second.

At the end the service is stopped (the next kind in turn) and restarted once more, and the
keyframes it holds are compared with the acknowledgements: a keyframe acknowledged as added,
never asked to be deleted and not held is *lost*; an id held twice is *duplicated*; one
acknowledged as removed but held again is *resurrected*. :func:`run_soak` returns the JSON
section; :mod:`.soak_report` summarises and draws it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ..eval.results import json_safe
from .machine import load_average, rss_mb
from .samples import JPEG_QUALITY, QuerySet
from .soak_ledger import Ledger, Outcomes, Phase
from .soak_report import STOP_KINDS, query_summary, restart_summary, rss_summary
from .soak_service import MAP_NAME, ServiceRunner

CAMERA_ID = "cam0"
#: First id of a streamed keyframe (the scene's own keyframes are 0..n-1).
STREAM_FIRST_ID = 1000
#: Pause before asking again after a "busy" reply (a journal replay takes about a second).
BUSY_RETRY_S = 0.2


@dataclass(frozen=True)
class SoakConf:
    """Sizes and rhythm of one soak run (the default is the run of docs/reliability.md: 600 s,
    a stop every 60 s)."""

    seconds: float = 600.0
    restart_every_s: float = 60.0
    query_clients: int = 4
    preset: str = "desk"
    scale: float = 0.5
    seed: int = 0
    method: str = "sbi+p3p"
    workers: int = 2
    queue_size: int = 8
    #: Journal records between snapshots: small, so that snapshots happen during the run.
    snapshot_every: int = 50
    fsync: bool = True
    stream_period_s: float = 1.0
    ack_timeout_s: float = 5.0
    delete_period_s: float = 1.0
    keep_streamed: int = 20
    query_timeout_s: float = 5.0
    #: SIGTERM is followed by kill -9 after this long (systemd's TimeoutStopSec is 60 s).
    stop_timeout_s: float = 90.0
    ready_timeout_s: float = 300.0
    rss_period_s: float = 1.0

    def __post_init__(self) -> None:
        if not (self.seconds > 0 and self.restart_every_s > 0 and self.query_clients >= 0):
            raise ValueError("soak: expected seconds > 0, restart_every_s > 0 and "
                             f"query_clients >= 0, got {self.seconds}, {self.restart_every_s}, "
                             f"{self.query_clients}")


@dataclass(eq=False)
class SoakScene:
    """What the soak needs of a scene: the camera, posed keyframe images ((H, W) uint8 grey,
    ``world_from_cam`` (4, 4)) and query JPEGs."""

    camera: Camera
    keyframe_images: list[npt.NDArray[np.uint8]]
    keyframe_poses: list[npt.NDArray[np.float64]]
    query_jpegs: list[bytes]
    info: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_images(cls, camera: Camera, keyframe_images: Sequence[npt.NDArray[np.uint8]],
                    keyframe_poses: Sequence[Any], query_images: Sequence[npt.NDArray[np.uint8]],
                    **info: Any) -> SoakScene:
        queries = QuerySet.from_images(camera, query_images, [np.eye(4)] * len(query_images))
        return cls(camera, list(keyframe_images), [np.asarray(p, np.float64)
                                                   for p in keyframe_poses],
                   queries.jpegs, dict(info, jpeg_quality=JPEG_QUALITY))


def render_scene(conf: SoakConf, tmp: Path) -> SoakScene:
    """The ``reloc synth`` preset ``conf.preset`` rendered at ``conf.scale``."""
    from ..data.dataset import read_dataset
    from ..synth import render_dataset

    root = render_dataset(conf.preset, tmp / "dataset", seed=conf.seed, scale=conf.scale,
                          progress=False)
    ds = read_dataset(root)
    camera = ds.camera(ds.map_entries[0])
    return SoakScene.from_images(
        camera, [ds.load_image(e) for e in ds.map_entries],
        [e.world_from_cam for e in ds.map_entries],
        [ds.load_image(e) for e in ds.query_entries],
        preset=conf.preset, scale=conf.scale, seed=conf.seed,
        image=f"{camera.width}x{camera.height}")


def classify(exc: BaseException) -> str:
    """An outcome name for a failed query: ``busy``, ``no_reply``, an ErrorCode, or the
    exception's type."""
    from reloc_client.client import NoReplyError, ServiceBusy, ServiceError

    if isinstance(exc, ServiceBusy):
        return "busy"
    if isinstance(exc, NoReplyError):
        return "no_reply"
    if isinstance(exc, ServiceError):
        return exc.code.value
    return type(exc).__name__


def query_loop(client: Any, jpegs: Sequence[bytes], phase: Phase, out: Outcomes, index: int,
               timeout_s: float) -> None:
    """Query back to back until ``phase.stop``. A query without a reply is counted as
    ``no_reply_restarting`` if the service was not up when it was sent or answered,
    ``no_reply_reconnecting`` if it was up but this client has not been answered since the
    restart (its session is still reconnecting), else ``no_reply_while_up``."""
    i, seen = index, phase.generation
    while not phase.stop.is_set():
        was_up = phase.up.is_set()
        try:
            result = client.relocalize(jpegs[i % len(jpegs)], camera_id=CAMERA_ID,
                                       timeout=timeout_s)
        except Exception as exc:  # every failure is an outcome to count, none is hidden
            kind = classify(exc)
            if kind == "no_reply":
                kind = no_reply_kind(was_up and phase.up.is_set(), seen < phase.generation)
            out.record(kind)
            phase.stop.wait(0.05 if kind == "busy" else 0.2)  # no busy loop while down
        else:
            seen = phase.answered(seen)
            out.record("ok" if result.ok else "not_relocalized", result.round_trip_s)
        i += 1


def no_reply_kind(up: bool, behind: bool) -> str:
    if not up:
        return "no_reply_restarting"
    return "no_reply_reconnecting" if behind else "no_reply_while_up"


def stream_loop(client: Any, scene: SoakScene, images: Sequence[Any], ledger: Ledger,
                phase: Phase, conf: SoakConf) -> None:
    """Put keyframes with new ids in order, each waited for until acknowledged (or
    ``ack_timeout_s``), one per ``stream_period_s``."""
    kf_id = STREAM_FIRST_ID
    while not phase.stop.is_set():
        start = time.monotonic()
        i = kf_id % len(images)
        with ledger.lock:
            ledger.sent.append(kf_id)
        with contextlib.suppress(Exception):  # a put to a stopped service raises nothing
            client.add_keyframe(kf_id, images[i], scene.keyframe_poses[i], camera_id=CAMERA_ID)
        ledger.wait_added(kf_id, conf.ack_timeout_s)
        kf_id += 1
        phase.stop.wait(max(0.0, conf.stream_period_s - (time.monotonic() - start)))


def delete_loop(client: Any, ledger: Ledger, phase: Phase, conf: SoakConf) -> None:
    """Delete the oldest acknowledged streamed keyframe whenever more than
    ``keep_streamed`` are in the map, one per ``delete_period_s``."""
    while not phase.stop.wait(conf.delete_period_s):
        kf_id = ledger.deletable(conf.keep_streamed)
        if kf_id is None:
            continue
        with ledger.lock:
            ledger.delete_sent.append(kf_id)
        with contextlib.suppress(Exception):
            client.remove_keyframe(kf_id)


def rss_loop(runner: ServiceRunner, phase: Phase, samples: list[list[Any]],
             period_s: float) -> None:
    """Sample the service's resident memory every ``period_s`` (None while it is down)."""
    while not phase.stop.wait(period_s):
        pid = runner.pid
        samples.append([round(phase.now(), 2), None if pid is None else rss_mb(pid=pid)])


# -- restarts ----------------------------------------------------------------------------------

def wait_answering(runner: ServiceRunner, jpeg: bytes, timeout_s: float) -> float:
    """Seconds from the process start to the first answered ``relocalize`` (ok or not
    relocalized); RuntimeError if the process exits, TimeoutError after ``timeout_s``."""
    from reloc_client.client import RelocClient

    deadline = runner.started_at + timeout_s
    client = None
    try:
        while time.monotonic() < deadline:
            if runner.exited() is not None:
                raise RuntimeError(f"the soak service exited with {runner.exited()}: "
                                   f"{runner.log_tail()}")
            try:
                client = client or RelocClient(runner.endpoint, map=MAP_NAME, timeout=2)
                client.relocalize(jpeg, camera_id=CAMERA_ID, timeout=2)
                return time.monotonic() - runner.started_at
            except Exception:  # not up yet: no session, no reply, not trained, busy
                time.sleep(0.1)
        raise TimeoutError(f"the soak service did not answer within {timeout_s} s")
    finally:
        if client is not None:
            client.close()


def restart(runner: ServiceRunner, kind: str, scene: SoakScene, phase: Phase,
            conf: SoakConf, audit: Callable[[], dict[str, Any]] | None = None
            ) -> dict[str, Any]:
    """Stop the service by ``kind``, start it again, wait until it answers; then
    ``audit()`` what it holds, if given."""
    phase.up.clear()
    at = phase.now()
    row = runner.stop(kind, conf.stop_timeout_s)
    runner.start()
    row.update(at_s=at, restart_s=wait_answering(runner, scene.query_jpegs[0],
                                                 conf.ready_timeout_s))
    phase.went_up()
    if audit is not None:
        try:
            row["audit"] = audit()
        except Exception as exc:  # recorded: an audit that cannot list is a finding too
            row["audit"] = {"error": f"{type(exc).__name__}: {exc}"}
    return row


def audit_held(list_held: Callable[[], list[int]], ledger: Ledger, base: int
               ) -> dict[str, Any]:
    """What a restarted service holds, under load: every keyframe acknowledged before the
    listing and not asked to be deleted by its end must be listed. (Without this, a keyframe
    lost at a restart would go unseen once the deleter asks to delete it.)"""
    with ledger.lock:
        acknowledged = set(ledger.added) | set(range(base))
    held = list_held()
    with ledger.lock:
        asked_deleted = set(ledger.delete_sent)
    lost = sorted(acknowledged - asked_deleted - set(held))
    return {"held": len(held), "lost_ids": lost,
            "duplicated": sum(n - 1 for n in Counter(held).values() if n > 1)}


# -- setup and the final count ---------------------------------------------------------------

def seed_map(client: Any, scene: SoakScene, images: Sequence[Any], ledger: Ledger,
             method: str) -> None:
    """Put the camera and the scene's keyframes (ids 0..n-1), wait for them, train."""
    client.set_camera(CAMERA_ID, scene.camera)
    for kf_id, image in enumerate(images):
        client.add_keyframe(kf_id, image, scene.keyframe_poses[kf_id], camera_id=CAMERA_ID)
    for kf_id in range(len(images)):
        if not ledger.wait_added(kf_id, 120):
            raise TimeoutError(f"soak setup: keyframe {kf_id} was not acknowledged in 120 s "
                               f"(rejected: {dict(ledger.rejected)})")
    reply = client.train(method=method, wait=True, timeout=600)
    if not reply.accepted:
        raise RuntimeError(f"soak setup: training was refused: {reply}")


def held_keyframes(runner: ServiceRunner, timeout_s: float = 60.0) -> list[int]:
    """Ids of the keyframes the service lists (with repeats, if any). "Busy" is retried, as
    its reply asks, until ``timeout_s``: a restarted service answers queries while it still
    replays its journal, and refuses a listing until the replay is done."""
    from reloc_client.client import RelocClient, ServiceBusy

    deadline = time.monotonic() + timeout_s
    with RelocClient(runner.endpoint, map=MAP_NAME, timeout=timeout_s) as client:
        while True:
            try:
                return [info.id for info in client.keyframes(timeout=timeout_s)]
            except ServiceBusy:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(BUSY_RETRY_S)


def keyframe_count(ledger: Ledger, base: int, held: Sequence[int],
                   audits: Sequence[Mapping[str, Any]] = ()) -> dict[str, Any]:
    """Compare what the service holds at the end (and held at each restart's ``audits``)
    with what was acknowledged."""
    present = set(held)
    asked_deleted = set(ledger.delete_sent)
    expected = set(range(base)) | (ledger.added - asked_deleted)
    lost_at_end = expected - present
    lost_in_audits = {k for a in audits for k in a.get("lost_ids", [])}
    lost = sorted(lost_at_end | lost_in_audits)
    dup_in_audits = sum(a.get("duplicated", 0) for a in audits)
    sent = set(ledger.sent) | set(range(base))
    return {
        "base": base, "streamed_sent": len(ledger.sent),
        "streamed_acknowledged": len(ledger.added & set(ledger.sent)),
        "streamed_unacknowledged": len(set(ledger.sent) - ledger.added),
        "delete_sent": len(asked_deleted), "delete_acknowledged": len(ledger.removed),
        "held_final": len(held), "lost": len(lost), "lost_ids": lost[:50],
        "lost_at_end": len(lost_at_end), "lost_in_audits": len(lost_in_audits),
        "audits": len(audits), "audits_failed": sum("error" in a for a in audits),
        "duplicated": sum(n - 1 for n in Counter(held).values() if n > 1) + dup_in_audits,
        "resurrected": len(ledger.removed & present),
        "unexpected": len(present - sent),
        "held_unacknowledged": len(present - ledger.added - set(range(base))),
        "repeated_added_events": sum(n - 1 for n in ledger.added_events.values() if n > 1),
        "rejected_by_code": dict(ledger.rejected)}


# -- the run -----------------------------------------------------------------------------------

def run_soak(conf: SoakConf, *, scene: SoakScene | None = None, workdir: Path | None = None,
             on_progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The soak run of ``conf`` (the scene of ``conf.preset`` unless ``scene`` is given);
    returns its JSON section. The service's logs and storage stay in ``workdir`` if given."""
    say = on_progress or (lambda _m: None)
    with contextlib.ExitStack() as stack:
        tmp = workdir or Path(stack.enter_context(tempfile.TemporaryDirectory(
            prefix="reloc-soak-")))
        tmp.mkdir(parents=True, exist_ok=True)
        if scene is None:
            say(f"rendering preset {conf.preset!r} at scale {conf.scale}")
            scene = render_scene(conf, tmp)
        runner = ServiceRunner(conf, tmp)
        try:
            return _run(conf, scene, runner, say)
        finally:
            if runner.exited() is None:
                runner.stop("kill9", 10)


def _run(conf: SoakConf, scene: SoakScene, runner: ServiceRunner,
         say: Callable[[str], None]) -> dict[str, Any]:
    from reloc_client.client import RelocClient, to_wire_image

    images = [to_wire_image(im) for im in scene.keyframe_images]  # encoded once
    ledger, phase = Ledger(), Phase()
    out = Outcomes(phase.now)
    load_at_start = load_average()
    runner.start()
    first_start_s = _wait_up(runner, conf)
    with contextlib.ExitStack() as stack:
        def client(timeout: float = conf.query_timeout_s) -> Any:
            return stack.enter_context(RelocClient(runner.endpoint, map=MAP_NAME,
                                                   timeout=timeout))

        subscriber = client()
        sub = subscriber.subscribe_events(ledger.on_event)
        stack.callback(sub.undeclare)
        time.sleep(0.3)  # the subscription reaches the service before the first put
        say(f"seeding the map ({len(images)} keyframes) and training {conf.method}")
        seed_map(client(30), scene, images, ledger, conf.method)
        first_ready_s = wait_answering(runner, scene.query_jpegs[0], conf.ready_timeout_s)
        phase.t0 = time.monotonic()
        phase.up.set()  # generation 0: every client starts answered
        samples: list[list[Any]] = []
        threads = [threading.Thread(target=query_loop, name=f"soak-query-{k}", daemon=True,
                                    args=(client(), scene.query_jpegs, phase, out, k,
                                          conf.query_timeout_s))
                   for k in range(conf.query_clients)]
        threads += [
            threading.Thread(target=stream_loop, name="soak-stream", daemon=True,
                             args=(client(), scene, images, ledger, phase, conf)),
            threading.Thread(target=delete_loop, name="soak-delete", daemon=True,
                             args=(client(), ledger, phase, conf)),
            threading.Thread(target=rss_loop, name="soak-rss", daemon=True,
                             args=(runner, phase, samples, conf.rss_period_s))]
        for t in threads:
            t.start()
        restarts = _supervise(conf, scene, runner, phase, say,
                              lambda: audit_held(lambda: held_keyframes(runner), ledger,
                                                 len(images)))
        phase.stop.set()
        for n, row in enumerate(restarts, start=1):
            resumed = phase.resumed_s.get(n, [])
            row.update(clients_resumed=len(resumed),
                       clients_resumed_max_s=max(resumed) if resumed else None)
        for t in threads:
            t.join(conf.query_timeout_s + conf.ack_timeout_s + 30)
        load_s = phase.now()
        kind = STOP_KINDS[len(restarts) % len(STOP_KINDS)]
        say(f"final stop ({kind}) and restart")
        time.sleep(1.0)  # the last events reach the subscriber
        final = restart(runner, kind, scene, phase, conf)
        held = held_keyframes(runner)
    return {"conf": dataclasses.asdict(conf), "scene": scene.info, "load_s": load_s,
            "first_start_s": first_start_s, "first_ready_s": first_ready_s,
            "queries": query_summary(out), "restarts": restarts,
            "restart_summary": restart_summary(restarts), "final_restart": final,
            "keyframes": keyframe_count(ledger, len(images), held,
                                        [r["audit"] for r in restarts if "audit" in r]),
            "events": dict(ledger.events), "rss": rss_summary(samples),
            "load_average_at_start": load_at_start, "load_average_at_end": load_average(),
            "note": "clients are threads of the benchmark process (their own Zenoh sessions, "
                    "client mode); the service is `reloc serve` in its own process; "
                    "`restart_s` is from the process start to the first answered query"}


def _wait_up(runner: ServiceRunner, conf: SoakConf) -> float:
    """Seconds until the freshly started service answers a status query on the map."""
    from .loopback import wait_ready

    assert runner.proc is not None
    wait_ready(runner.proc, runner.endpoint, map_name=MAP_NAME,
               log=runner.folder / f"service-{runner.runs:02d}.log",
               timeout=conf.ready_timeout_s)
    return time.monotonic() - runner.started_at


def _supervise(conf: SoakConf, scene: SoakScene, runner: ServiceRunner, phase: Phase,
               say: Callable[[str], None], audit: Callable[[], dict[str, Any]]
               ) -> list[dict[str, Any]]:
    """Stop and restart the service every ``restart_every_s`` until ``seconds`` are over."""
    rows: list[dict[str, Any]] = []
    next_at = conf.restart_every_s
    while True:
        wait = min(next_at, conf.seconds) - phase.now()
        if wait > 0:
            time.sleep(wait)
        if phase.now() >= conf.seconds:
            return rows
        if runner.exited() is not None:
            raise RuntimeError(f"the soak service died on its own ({runner.exited()}): "
                               f"{runner.log_tail()}")
        kind = STOP_KINDS[len(rows) % len(STOP_KINDS)]
        row = restart(runner, kind, scene, phase, conf, audit)
        rows.append(row)
        say(f"{kind} at {row['at_s']:.0f} s: stopped in {row['stop_s']:.1f} s (exit "
            f"{row['exit_code']}), answering again after {row['restart_s']:.1f} s; holds "
            f"{row['audit'].get('held')} keyframes, lost {row['audit'].get('lost_ids')}")
        next_at = max(next_at + conf.restart_every_s, phase.now() + 1.0)


def run_into(result: dict[str, Any], conf: SoakConf, workdir: Path | None,
             say: Callable[[str], None]) -> None:
    """Run the soak into ``result["soak"]`` (an ``{"error": ...}`` if it failed)."""
    import traceback

    start = time.perf_counter()
    try:
        result["soak"] = json_safe(run_soak(conf, workdir=workdir and workdir / "soak",
                                            on_progress=say))
    except Exception as exc:  # the error is the section's result, as for the others
        traceback.print_exc()
        result["soak"] = {"error": f"{type(exc).__name__}: {exc}"}
        return
    result.setdefault("section_seconds", {})["soak"] = time.perf_counter() - start
