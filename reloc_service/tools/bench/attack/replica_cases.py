"""Replica cases: two ``reloc serve`` processes serving map lab behind a ``reloc router``. A
replica follows only a peer serving its map's identity, a lagging replica catches up, and an
acknowledgement names the replicas that stored a keyframe and the one that refused it."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..loopback import free_port
from .harness import (
    CAMERA_ID,
    MAP_NAME,
    READY_TIMEOUT_S,
    REPLY_TIMEOUT_S,
    Arena,
    AttackService,
    Attempt,
    TinyScene,
    broke,
    clean,
    compare_held,
    held_ids,
    put_acknowledged,
    register,
)

#: Seconds between a replica's comparisons with its peers (the service's default is 5 s).
REPLICA_CHECK_S = 1.0


@contextlib.contextmanager
def router(folder: Path) -> Iterator[str]:
    """``reloc router`` on a free loopback port for the block; yields its endpoint."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with open(folder / "router.log", "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "router",
                                 "--listen", endpoint], stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 1):
                break
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"reloc router did not listen on {endpoint} "
                                   f"(exit {proc.poll()}; see {folder / 'router.log'})")
            time.sleep(0.2)
        yield endpoint
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def replica(folder: Path, router_endpoint: str, **quotas: int) -> AttackService:
    """A service serving lab that joins the router, bootstraps from a peer serving lab and
    compares with its peers every :data:`REPLICA_CHECK_S` seconds."""
    return AttackService(folder, connect=[router_endpoint], quotas=quotas or None,
                         service={"bootstrap_from_peers": True,
                                  "replica_check_s": REPLICA_CHECK_S})


def statuses(client: Any, content_hash: bool = True) -> dict[str, Any]:
    """Every instance's status of the client's map (instance -> StatusReply)."""
    import zenoh
    from reloc_client import protocol as wire

    key = wire.keys.status(client.prefix, client.map)
    selector = f"{key}?content_hash=true" if content_hash else key
    out = {}
    for reply in client.session.get(selector, timeout=REPLY_TIMEOUT_S,
                                    target=zenoh.QueryTarget.ALL,
                                    consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is not None:
            status = wire.StatusReply.decode(reply.ok.payload.to_bytes(), client.limits)
            out[status.instance] = status
    return out


def wait_routed(client: Any, *instances: str, timeout: float = READY_TIMEOUT_S) -> None:
    """Wait until every one of ``instances`` answers ``client`` through the router: a service
    answers on its own endpoint before the router routes to it, and a put sent before then
    never reaches it (a replica catches up later, but the case judges acknowledgements)."""
    deadline = time.monotonic() + timeout
    while not set(instances) <= set(statuses(client, content_hash=False)):
        if time.monotonic() > deadline:
            raise TimeoutError(f"instances {sorted(instances)} not reachable through the router "
                               f"within {timeout:.0f} s")
        time.sleep(0.5)


def wait_status(client: Any, instance: str, accept: Any, timeout: float = 60.0) -> Any:
    """``instance``'s status once ``accept(status)`` holds, or its last status (None if it
    never answered) after ``timeout`` seconds."""
    deadline, last = time.monotonic() + timeout, None
    while True:
        last = statuses(client).get(instance, last)
        if (last is not None and accept(last)) or time.monotonic() > deadline:
            return last
        time.sleep(0.5)


def put_shifted(client: Any, scene: TinyScene, ids: range, dx: float) -> None:
    """Keyframes ``ids`` with their poses moved ``dx`` metres along x (another map's)."""
    client.set_camera(CAMERA_ID, scene.camera, wait=True)
    for kf_id in ids:
        world_from_cam = scene.pose(kf_id)
        world_from_cam[0, 3] += dx
        client.add_keyframe(kf_id, scene.image(kf_id), world_from_cam, camera_id=CAMERA_ID,
                            wait=True)


def alone(service: AttackService, scene: TinyScene, ids: range) -> str:
    """Fill ``service``'s lab with ``ids`` while it serves alone; stop it; its map identity."""
    service.start()
    try:
        with service.client() as c:
            put_acknowledged(c, scene, ids)
            return str(c.status().map_id)
    finally:
        service.stop("sigterm")


@register("replica-another-map", "replica",
          "a replica holding lab (4 keyframes) joins a peer serving another lab (2 keyframes, "
          "poses 0.5 m away), at its start and again after a restart: it keeps its own 4 and "
          "its identity, its status names the peer's identity as diverged; the peer untouched")
def replica_another_map(arena: Arena) -> list[Attempt]:
    folder = arena.case_folder("replica-another-map")
    with router(folder) as hub:
        own = replica(folder / "replica", hub)
        own_id = alone(own, arena.scene, range(4))
        peer = AttackService(folder / "peer", connect=[hub]).start()
        attempts = []
        try:
            with peer.client() as c:
                put_shifted(c, arena.scene, range(2), 0.5)
                peer_id = c.status().map_id
            for run in range(2):
                own.start()
                try:
                    with own.client() as c:
                        status = wait_status(c, own.instance, lambda s: bool(s.diverged))
                        peer_status = statuses(c).get(peer.instance)
                finally:
                    own.stop("sigterm")
                attempts.append(judge_identity(run, status, peer_status, own_id, peer_id))
        finally:
            peer.stop("sigterm")
    return attempts


def judge_identity(run: int, status: Any, peer_status: Any, own_id: str, peer_id: str
                   ) -> Attempt:
    what = f"start {run + 1}"
    if status is None or peer_status is None:
        return broke(f"{what}: no status from {'the replica' if status is None else 'the peer'}")
    if status.map_id != own_id or status.keyframes != 4:
        return broke(f"{what}: the replica serves map {status.map_id} with {status.keyframes} "
                     f"keyframes (its own: {own_id} with 4)")
    if peer_id not in status.diverged:
        return broke(f"{what}: diverged {status.diverged!r} does not name the peer's {peer_id}")
    if peer_status.keyframes != 2 or peer_status.map_id != peer_id:
        return broke(f"{what}: the peer now serves {peer_status.keyframes} keyframes as "
                     f"{peer_status.map_id}")
    return clean(f"{what}: kept its 4 keyframes and identity; diverged: {status.diverged[:90]}")


@register("replica-catch-up", "replica",
          "a replica bootstraps lab (4 keyframes) from its peer, is stopped while 4 more are "
          "acknowledged by the peer, restarts: it catches up to all 8 with the peer's identity "
          "and content hash")
def replica_catch_up(arena: Arena) -> list[Attempt]:
    folder = arena.case_folder("replica-catch-up")
    with router(folder) as hub:
        peer = AttackService(folder / "peer", connect=[hub]).start()
        late = replica(folder / "replica", hub)
        try:
            with peer.client() as c:
                put_acknowledged(c, arena.scene, range(4))
            late.start()
            with late.client() as c:
                first = wait_status(c, late.instance, lambda s: s.keyframes == 4)
            late.stop("sigterm")
            with peer.client() as c:
                put_acknowledged(c, arena.scene, range(4, 8))
            late.start()
            with late.client() as c:
                caught = wait_status(c, late.instance, lambda s: s.keyframes == 8)
                mine = statuses(c)
            late.stop("sigterm")
        finally:
            late.stop("sigterm")
            peer.stop("sigterm")
    reference = mine.get(peer.instance)
    if first is None or caught is None or reference is None:
        return [broke("no status from the replica or the peer")]
    steps = f"bootstrap {first.keyframes} keyframes, after the restart {caught.keyframes}"
    if caught.keyframes != 8 or caught.map_id != reference.map_id:
        return [broke(f"{steps} (expected 8) as {caught.map_id} (peer {reference.map_id})")]
    if caught.content_hash != reference.content_hash:
        return [broke(f"{steps}, content hash {caught.content_hash[:12]} != the peer's "
                      f"{reference.content_hash[:12]}")]
    return [clean(f"{steps}; identity and content hash equal to the peer's")]


@contextlib.contextmanager
def two_replicas(folder: Path, scene: TinyScene, full_service: Callable[[str], AttackService]
                 ) -> Iterator[tuple[Any, AttackService, AttackService]]:
    """Behind a ``reloc router``: the service ``full_service(router endpoint)`` makes and a
    replica of lab, both started, and a client through the router that both answer (a put
    sent before the router routes to an instance never reaches it), the scene's camera set;
    yields (client, full, other) and stops both services after the block."""
    from reloc_client.client import RelocClient

    with router(folder) as hub:
        full = full_service(hub).start()
        other = replica(folder / "replica", hub).start()
        try:
            with RelocClient(hub, map=MAP_NAME, timeout=REPLY_TIMEOUT_S) as client:
                wait_routed(client, full.instance, other.instance)
                client.set_camera(CAMERA_ID, scene.camera, wait=True)
                yield client, full, other
        finally:
            other.stop("sigterm")
            full.stop("sigterm")


def put_each(client: Any, scene: TinyScene, ids: range
             ) -> Iterator[tuple[int, tuple[str, ...], Exception | None]]:
    """``add_keyframe(wait=True, replicas=2)`` of each of ``ids`` in turn: (id, the instances
    that stored it, None), or (id, (), the ServiceError) when the put was refused."""
    from reloc_client.client import ServiceError

    for kf_id in ids:
        try:
            names = tuple(client.add_keyframe(kf_id, scene.image(kf_id), scene.pose(kf_id),
                                              camera_id=CAMERA_ID, wait=True, replicas=2))
        except ServiceError as exc:
            yield kf_id, (), exc
        else:
            yield kf_id, names, None


@register("replica-refuses", "replica",
          "two replicas of lab, one of them refusing writes (a keyframe quota of 4 standing "
          "in for a full disk); add_keyframe(wait=True, replicas=2) of 6 keyframes: 4 stored by "
          "both, keyframes 4-5 raise naming who stored them and who refused; nothing the "
          "client was told is stored is missing")
def replica_refuses(arena: Arena) -> list[Attempt]:
    folder = arena.case_folder("replica-refuses")
    attempts = []

    def quota_of_4(hub: str) -> AttackService:
        return AttackService(folder / "full", connect=[hub], quotas={"max_keyframes_per_map": 4})

    with two_replicas(folder, arena.scene, quota_of_4) as (c, full, other):
        told: dict[int, tuple[str, ...]] = {}
        for kf_id, names, error in put_each(c, arena.scene, range(6)):
            if error is None:
                told[kf_id] = names
                attempts.append(judge_stored(kf_id, names, kf_id < 4, full.instance,
                                             other.instance, ""))
            else:
                # The error names the instances that did store it: they must hold it.
                told[kf_id] = tuple(n for n in (full.instance, other.instance)
                                    if f"stored by ['{n}']" in str(error))
                attempts.append(judge_stored(kf_id, (), kf_id < 4, full.instance,
                                             other.instance, str(error)))
        for service in (full, other):
            with service.client() as sc:
                expected = {k for k, held_by in told.items() if service.instance in held_by}
                held = held_ids(sc, timeout=REPLY_TIMEOUT_S)
                attempts.append(compare_held(service.instance, held & expected, expected))
    return attempts


def judge_stored(kf_id: int, names: tuple[str, ...], both: bool, full: str, other: str,
                 error: str) -> Attempt:
    """Keyframes under the quota: stored by both, named; above it: an error naming the
    refusing instance (with QUOTA_EXCEEDED) and the one that stored it."""
    what = f"keyframe {kf_id}"
    if both:
        if sorted(names) == sorted((full, other)):
            return clean(f"{what}: stored by {sorted(names)}")
        return broke(f"{what}: {error or f'stored by {sorted(names)}'} (expected both)")
    if error and full in error and other in error and "QUOTA_EXCEEDED" in error:
        return clean(f"{what}: {error[:160]}")
    return broke(f"{what}: {error or f'stored by {sorted(names)}'} (expected an error naming "
                 f"{full} refusing with QUOTA_EXCEEDED and {other} storing it)")


@contextlib.contextmanager
def small_disk(path: Path, size: str = "8m") -> Iterator[bool]:
    """A tmpfs of ``size`` mounted at ``path`` for the block (True), or False where this
    process may not mount one (not root): the case is then not run."""
    path.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                             capture_output=True).returncode == 0
    try:
        yield mounted
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(path: Path) -> Path:
    """Write zeros to ``path`` until its file system is full (ENOSPC); the filler file."""
    filler = path / "filler"
    block = bytes(64 * 1024)
    with contextlib.suppress(OSError), open(filler, "wb") as out:
        while True:
            out.write(block)
            out.flush()
    with contextlib.suppress(OSError), open(filler, "ab") as out:   # the last partial block
        while True:
            out.write(b"\0" * 512)
            out.flush()
    return filler


@register("replica-disk-full", "replica",
          "two replicas of lab, one on a tmpfs filled to ENOSPC after 4 keyframes; "
          "add_keyframe(wait=True, replicas=2) of 2 more: each raises naming the full replica "
          "(STORAGE_ERROR) and the one that stored it; space freed: the full replica catches "
          "up to all 6 (not run where tmpfs cannot be mounted)")
def replica_disk_full(arena: Arena) -> list[Attempt]:
    folder = arena.case_folder("replica-disk-full")
    attempts = []

    def on_small_disk(hub: str) -> AttackService:
        return AttackService(folder / "full", folder / "disk" / "storage", connect=[hub],
                             service={"bootstrap_from_peers": True,
                                      "replica_check_s": REPLICA_CHECK_S})

    with small_disk(folder / "disk") as mounted:
        if not mounted:
            return []
        with two_replicas(folder, arena.scene, on_small_disk) as (c, full, other):
            for _kf_id, _names, error in put_each(c, arena.scene, range(4)):
                if error is not None:
                    raise error
            filler = fill(folder / "disk")
            for kf_id, names, error in put_each(c, arena.scene, range(4, 6)):
                attempts.append(
                    broke(f"keyframe {kf_id}: stored by {sorted(names)} on a full disk")
                    if error is None else
                    judge_full(kf_id, str(error), full.instance, other.instance))
            filler.unlink()
            caught = wait_status(c, full.instance, lambda s: s.keyframes == 6)
            reference = statuses(c).get(other.instance)
        attempts.append(judge_caught_up(caught, reference))
    return attempts


def judge_full(kf_id: int, error: str, full: str, other: str) -> Attempt:
    if full in error and f"stored by ['{other}']" in error and "STORAGE_ERROR" in error:
        return clean(f"keyframe {kf_id}: {error[:160]}")
    return broke(f"keyframe {kf_id}: {error[:200]} (expected {full} refusing with "
                 f"STORAGE_ERROR, {other} storing it)")


def judge_caught_up(caught: Any, reference: Any) -> Attempt:
    if caught is None or reference is None:
        return broke("after freeing space: no status from a replica")
    what = f"after freeing space: {caught.keyframes} keyframes (the peer {reference.keyframes})"
    if caught.keyframes != reference.keyframes or caught.content_hash != reference.content_hash:
        return broke(f"{what}, content hash equal: {caught.content_hash == reference.content_hash}")
    return clean(f"{what}, caught up, content hash equal")
