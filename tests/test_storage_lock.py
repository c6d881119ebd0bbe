"""One owner per storage and per map directory: a second service refuses to start naming the
holder, a lock left by a killed process is taken over, a writing tool refuses a map a running
service holds, and read-only inspection goes ahead saying who holds it.

Real processes (``reloc serve`` and small holders in subprocesses), real lock files, real
services on loopback (multicast scouting off)."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from reloc_client.client import RelocClient
from service_support import (
    MAP,
    ROOT,
    ServiceProcess,
    endpoint,
    free_port,
    service_conf,
    wait_until,
    write_config,
)

from reloc_service.cli.main import main as reloc_main
from reloc_service.service.app import Service
from reloc_service.service.map_dirs import map_dirname
from reloc_service.storage.lock import LOCK_FILE, DirectoryLock, LockHeld, holder_if_locked

#: A process that takes the lock of the directory in argv[1], says so, then waits.
HOLDER = """
import sys, time
from pathlib import Path
from reloc_service.storage.lock import DirectoryLock
DirectoryLock(Path(sys.argv[1]), what="storage").acquire("test holder")
print("held", flush=True)
time.sleep(120)
"""


def start_holder(directory: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(directory)], cwd=ROOT,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def files_of(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


# -- the lock itself --------------------------------------------------------------------------

def test_a_held_lock_is_refused_naming_its_holder_and_nothing_is_written(tmp_path):
    holder = start_holder(tmp_path)
    try:
        before = files_of(tmp_path)
        with pytest.raises(LockHeld) as err:
            DirectoryLock(tmp_path, what="storage").acquire("second")
        assert err.value.holder is not None and err.value.holder.pid == holder.pid
        assert f"pid {holder.pid} on host" in str(err.value) and "test holder" in str(err.value)
        assert files_of(tmp_path) == before
        probed = holder_if_locked(tmp_path)          # read-only probe: who, writes nothing
        assert probed is not None and probed.pid == holder.pid
        assert files_of(tmp_path) == before
    finally:
        holder.kill()
        holder.wait(10)


def test_a_lock_of_a_killed_process_is_taken_over_at_once_and_its_holder_logged(tmp_path,
                                                                                 caplog):
    holder = start_holder(tmp_path)
    holder.send_signal(signal.SIGKILL)
    holder.wait(10)
    assert holder_if_locked(tmp_path) is None
    start = time.monotonic()
    with caplog.at_level(logging.WARNING), DirectoryLock(tmp_path, what="storage").acquire(
            "next owner"):
        assert time.monotonic() - start < 0.2       # no waiting for a timeout
        record = json.loads((tmp_path / LOCK_FILE).read_text())
        assert record["pid"] == os.getpid() and record["purpose"] == "next owner"
    assert f"previous holder, pid {holder.pid} on host" in caplog.text
    assert "gone without releasing" in caplog.text


def test_a_clean_release_leaves_no_record_to_report(tmp_path, caplog):
    DirectoryLock(tmp_path, what="storage").acquire("first").release()
    assert (tmp_path / LOCK_FILE).read_bytes() == b""
    with caplog.at_level(logging.WARNING):
        DirectoryLock(tmp_path, what="storage").acquire("second").release()
    assert "previous holder" not in caplog.text


# -- services ---------------------------------------------------------------------------------

def serve_once(config: Path, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """``reloc serve --config config`` expected to exit by itself (it is killed otherwise)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                             "--config", str(config)], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"the second service did not refuse to start: {err[-2000:]}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def put_acknowledged(client: RelocClient, scene, ids: range) -> None:
    for kf_id in ids:
        i = kf_id % len(scene.keyframe_images)
        client.add_keyframe(kf_id, scene.keyframe_images[i], scene.keyframe_poses[i],
                            camera_id="cam0", wait=True)


def test_reloc_serve_refuses_a_storage_a_running_service_holds(tmp_path):
    port = free_port()
    config = write_config(tmp_path, free_port())
    service = Service(service_conf(port, tmp_path / "storage", maps=(MAP,))).start()
    try:
        before = files_of(tmp_path / "storage")
        refused = serve_once(config)
        assert refused.returncode == 1
        assert refused.stderr.startswith("reloc serve: error: storage ")
        assert f"in use by pid {os.getpid()} on host" in refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
        assert files_of(tmp_path / "storage") == before
        with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
            assert client.status().keyframes == 0       # the holder still serves
    finally:
        service.stop(final_snapshot=False)


@pytest.mark.slow
def test_a_second_service_on_the_same_storage_refuses_naming_the_holder(synthetic_scene,
                                                                         tmp_path):
    port = free_port()
    first = ServiceProcess(write_config(tmp_path, port, snapshot_every=0), port,
                           tmp_path / "first.log")
    try:
        assert first.client is not None
        first.client.set_camera("cam0", synthetic_scene.camera, wait=True)
        put_acknowledged(first.client, synthetic_scene, range(0, 20))
        before = files_of(tmp_path / "storage")
        second_dir = tmp_path / "second"
        second_dir.mkdir()
        second_config = write_config(second_dir, free_port())
        second_config.write_text(second_config.read_text().replace(
            str(second_dir / "storage"), str(tmp_path / "storage")))
        start = time.monotonic()
        refused = serve_once(second_config)
        print(f"second service refused in {time.monotonic() - start:.1f} s, exit "
              f"{refused.returncode}: {refused.stderr.strip()}")
        assert refused.returncode != 0
        assert f"in use by pid {first.proc.pid} on host" in refused.stderr
        assert "Traceback" not in refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
        assert files_of(tmp_path / "storage") == before
        put_acknowledged(first.client, synthetic_scene, range(20, 40))   # still serving
        assert first.terminate() == 0
    finally:
        first.close()
    restarted = ServiceProcess(write_config(tmp_path, port), port, tmp_path / "restart.log")
    try:
        assert restarted.client is not None
        assert {info.id for info in restarted.client.keyframes()} == set(range(40))
    finally:
        assert restarted.terminate() == 0


@pytest.mark.slow
def test_a_service_killed_with_sigkill_leaves_a_lock_the_next_one_takes_over(tmp_path):
    port = free_port()
    config = write_config(tmp_path, port)
    killed = ServiceProcess(config, port, tmp_path / "killed.log")
    pid = killed.proc.pid
    killed.kill9()
    record = json.loads((tmp_path / "storage" / LOCK_FILE).read_text())
    assert record["pid"] == pid                 # the record survives; the flock does not
    successor = ServiceProcess(config, port, tmp_path / "successor.log")
    try:
        assert successor.client is not None and successor.client.status().keyframes == 0
        log = (tmp_path / "successor.log").read_text()
        assert f"previous holder, pid {pid} on host" in log
    finally:
        assert successor.terminate() == 0


# -- a writing tool and a map a service holds ---------------------------------------------------

def test_a_map_a_service_holds_is_refused_to_writing_tools_and_inspected_read_only(
        tmp_path, capsys):
    storage = tmp_path / "storage"
    service = Service(service_conf(free_port(), storage, maps=(MAP,))).start()
    map_dir = storage / map_dirname(MAP)
    try:
        before = files_of(map_dir)
        assert reloc_main(["map", "set-current", str(map_dir), "1"]) == 1
        err = capsys.readouterr().err
        assert f"refused: map directory {map_dir} is in use by pid {os.getpid()}" in err
        assert "reloc serve" in err
        assert files_of(map_dir) == before
        assert reloc_main(["map", "check", str(map_dir)]) == 0
        out, err = capsys.readouterr()
        assert f"{map_dir}: ok" in out
        assert f"is in use by pid {os.getpid()}" in err and "read-only inspection" in err
    finally:
        service.stop(final_snapshot=False)
    assert reloc_main(["map", "check", str(map_dir)]) == 0
    assert "in use" not in capsys.readouterr().err


def test_set_current_repairs_a_map_no_service_holds(synthetic_scene, tmp_path, capsys):
    storage = tmp_path / "storage"
    port = free_port()
    service = Service(service_conf(port, storage, maps=(MAP,), snapshot_every=0,
                                   train_on_load=False)).start()
    try:
        with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
            client.set_camera("cam0", synthetic_scene.camera, wait=True)
            put_acknowledged(client, synthetic_scene, range(3))
            wait_until(lambda: service.maps[MAP].map_state().keyframes, timeout=30)
        service.maps[MAP].start_snapshot(wait=True)
    finally:
        service.stop(final_snapshot=False)
    map_dir = storage / map_dirname(MAP)
    snapshot = (map_dir / "map" / "CURRENT").read_text().strip().split("/")[-1]
    (map_dir / "map" / "CURRENT").unlink()
    (map_dir / "service.json").unlink()     # the service cannot tell which snapshot: fails
    assert reloc_main(["map", "set-current", str(map_dir), snapshot]) == 0
    assert "every file verified" in capsys.readouterr().out
    assert (map_dir / "map" / "CURRENT").read_text().strip().endswith(snapshot)
    assert holder_if_locked(map_dir) is None
