"""What many maps created by puts cost a ``reloc serve`` process: threads, resident memory
(the service and its worker processes) and open files once N maps are created by one small
valid keyframe put each, and again after a restart on the same storage.

    python scripts/new_maps_cost.py [--maps 300] [--root CHECKOUT] [--max-maps N]

``--root`` runs the service of another checkout (e.g. the main branch, to compare);
``--max-maps`` writes ``[quotas] max_maps`` (only for a service that knows quotas).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import zenoh
from reloc_client import protocol as wire

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def tiny_put(rng: np.random.Generator) -> bytes:
    """A valid keyframe put of about 800 bytes: a 32x24 PNG of noise, its camera inline."""
    ok, png = cv2.imencode(".png", rng.integers(0, 255, (24, 32), dtype=np.uint8))
    assert ok
    camera = wire.WireCamera.from_dict({"model": "pinhole", "width": 32, "height": 24,
                                        "fx": 25.0, "fy": 25.0, "cx": 15.5, "cy": 11.5})
    return wire.KeyframePut(id=0, image=wire.WireImage.from_bytes(png.tobytes()),
                            world_from_cam=wire.WirePose.from_matrix(np.eye(4)),
                            camera=camera).encode()


def session(port: int, timeout: float = 120.0) -> zenoh.Session:
    """A client session to the service on ``port``, once it listens."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return _open(port)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def _open(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def start(root: Path, config: Path, log: Path) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": f"{root}:{root / 'clients'}"}
    return subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                             "--config", str(config)], cwd=root, env=env,
                            stdout=log.open("ab"), stderr=subprocess.STDOUT)


def served(s: zenoh.Session, names: list[str], timeout: float) -> str:
    """Wait until every map in ``names`` answers ``status`` (or an error); how many did."""
    deadline = time.monotonic() + timeout
    left, errors = list(names), 0
    while left and time.monotonic() < deadline:
        still = []
        for name in left:
            replies = list(s.get(wire.keys.status("reloc", name), timeout=2))
            if not replies:
                still.append(name)
            errors += any(r.ok is None for r in replies)
        left = still
        if left:
            time.sleep(0.5)
    return f"{len(names) - len(left) - errors} served, {errors} errors, {len(left)} silent"


def measure(pid: int) -> dict[str, int]:
    """Threads and open files of the service; resident memory of it and its children."""
    def field(p: int, name: str) -> int:
        for line in Path(f"/proc/{p}/status").read_text().splitlines():
            if line.startswith(name + ":"):
                return int(line.split()[1])
        return 0

    children = [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    rss_kb = field(pid, "VmRSS") + sum(field(c, "VmRSS") for c in children
                                       if Path(f"/proc/{c}").exists())
    return {"threads": field(pid, "Threads"), "rss_mb": rss_kb // 1024,
            "open_files": len(os.listdir(f"/proc/{pid}/fd")), "children": len(children)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", type=int, default=300)
    parser.add_argument("--root", type=Path, default=REPO)
    parser.add_argument("--max-maps", type=int, default=0)
    args = parser.parse_args()
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="reloc-maps-") as tmp:
        config = Path(tmp) / "service.toml"
        lines = ["[zenoh]", 'mode = "peer"', f'listen = ["tcp/127.0.0.1:{port}"]',
                 "multicast_scouting = false", "[service]", 'instance = "maps"',
                 f'storage = "{tmp}/storage"', "train_on_load = false",
                 # every map's final snapshot at the stop, on a loaded machine
                 "stop_timeout_s = 55.0"]
        if args.max_maps:
            lines += ["[quotas]", f"max_maps = {args.max_maps}"]
        config.write_text("\n".join(lines) + "\n")
        log = Path(tmp) / "log.txt"
        names = [f"m{i:04d}" for i in range(args.maps)]
        rng = np.random.default_rng(0)
        proc = start(args.root, config, log)
        try:
            with session(port) as s:
                time.sleep(3)
                idle = measure(proc.pid)
                t0 = time.monotonic()
                for name in names:
                    s.put(wire.keys.keyframe("reloc", name, 0), tiny_put(rng),
                          congestion_control=zenoh.CongestionControl.BLOCK)
                ok = served(s, names, 600)
                created_s = time.monotonic() - t0
                time.sleep(2)
                after = measure(proc.pid)
            proc.send_signal(signal.SIGTERM)
            proc.wait(120)
            proc = start(args.root, config, log)
            with session(port) as s:
                time.sleep(3)
                restored = served(s, names, 600)
                time.sleep(2)
                again = measure(proc.pid)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(120)
            text = log.read_text().splitlines()
            errors = [line for line in text if " ERROR " in line]
            stops = [line for line in text if "stopped in" in line]
            unfinished = sum("did not finish" in line for line in text)
    print(f"root {args.root}: {args.maps} maps created by puts: {ok} in {created_s:.1f} s; "
          f"served after restart: {restored}")
    for line in [*errors[:3], *stops]:
        print(f"  log: {line[:300]}")
    print(f"  final snapshots not finished within the stop budget: {unfinished}")
    for label, m in (("idle", idle), (f"{args.maps} maps", after), ("after restart", again)):
        print(f"  {label:>14}: {m['threads']} threads, {m['rss_mb']} MB resident (service "
              f"and {m['children']} children), {m['open_files']} open files")
    return 0


if __name__ == "__main__":
    sys.exit(main())
