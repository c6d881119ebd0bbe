"""Bytes per keyframe of each part of a map a service saved: upload a dataset with its depth
maps, train, stop with SIGTERM, then list the storage by part and by snapshot file.

    .venv/bin/python scripts/map_size_parts.py /work/data/room --out /tmp/size \\
        [--set 'descriptor_codec = "pq"'] [--set 'keyframe_descriptors = "per-landmark"']
        [--set 'stop_timeout_s = 280.0'] [--files]

The dataset's ``truth_depth.txt`` is sent as its ``depth.txt`` (a rendered set's depth maps,
as an RGB-D user would send them) unless it has its own. ``--set KEY=VALUE`` adds a line to
the service's ``[service]`` table (TOML value): a loaded machine may need a longer
``stop_timeout_s`` for the final snapshot (past it the map stays in its journal, and the
script says so by listing no snapshot file). Prints one JSON object: keyframes, total kB a
keyframe, kB a keyframe per part (``reloc map info``'s kinds) and, with ``--files``, per
snapshot file (models and feature columns by name)."""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def staged_dataset(dataset: Path, work: Path) -> Path:
    """A copy of ``dataset``'s text files with its images and depth linked, and a
    ``depth.txt`` (its ground-truth depth when it has none of its own)."""
    staged = work / "dataset"
    shutil.rmtree(staged, ignore_errors=True)
    staged.mkdir(parents=True)
    for entry in dataset.iterdir():
        (staged / entry.name).symlink_to(entry.resolve())
    if not (dataset / "depth.txt").is_file():
        (staged / "depth.txt").unlink(missing_ok=True)
        shutil.copy(dataset / "truth_depth.txt", staged / "depth.txt")
    return staged


def serve_config(work: Path, port: int, settings: list[str]) -> Path:
    path = work / "serve.toml"
    path.write_text("\n".join([
        "[zenoh]", 'mode = "peer"', f'listen = ["tcp/127.0.0.1:{port}"]',
        "multicast_scouting = false", "[service]", 'instance = "map-size"',
        f'storage = "{work / "storage"}"', *settings, "[maps.lab]", ""]))
    return path


def client(port: int, *argv: str, timeout: float = 1800) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN / "reloc-client"), "--connect", f"tcp/127.0.0.1:{port}",
                           "--map", "lab", "--timeout", "600", *argv],
                          capture_output=True, text=True, timeout=timeout)


def upload_and_stop(dataset: Path, work: Path, settings: list[str]) -> None:
    """``reloc serve``; upload ``dataset`` with --train --wait; SIGTERM; wait for the exit."""
    port = free_port()
    proc = subprocess.Popen([str(BIN / "reloc"), "serve", "--config",
                             str(serve_config(work, port, settings))],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while client(port, "status", timeout=120).returncode != 0:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the service never answered status")
            time.sleep(0.5)
        up = client(port, "upload", str(dataset), "--train", "--wait")
        if up.returncode != 0:
            raise RuntimeError(f"upload failed: {up.stderr[-800:]}")
    finally:
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=300)
    (work / "serve.stderr").write_text(stderr)
    if proc.returncode != 0:
        raise RuntimeError(f"serve exited {proc.returncode}: {stderr[-800:]}")


def file_sizes(map_dir: Path) -> dict[str, int]:
    """Bytes of each file of the current snapshot, by path relative to it (models and
    feature columns named; images, depth and thumbnails summed by folder)."""
    snap_root = map_dir / "map"
    if not (snap_root / "CURRENT").is_file():
        return {}   # no snapshot: the map is all journal (the stop did not snapshot it)
    current = (snap_root / "CURRENT").read_text().strip()
    snapshot = snap_root / current
    sizes: dict[str, int] = {}
    for path in snapshot.rglob("*"):
        if path.is_file():
            rel = path.relative_to(snapshot)
            key = str(rel) if rel.parts[0] in ("models", "features", "landmarks") else rel.parts[0]
            sizes[key] = sizes.get(key, 0) + path.stat().st_size
    return sizes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--out", type=Path, required=True, help="work directory (replaced)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--files", action="store_true", help="also list snapshot files")
    args = parser.parse_args()
    work = args.out.resolve()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    upload_and_stop(staged_dataset(args.dataset.resolve(), work), work, args.set)
    info = json.loads(subprocess.run(
        [str(BIN / "reloc"), "map", "info", "--storage", str(work / "storage"), "lab",
         "--json"], capture_output=True, text=True, check=True).stdout)
    n = int(info["keyframes"])
    out = {"keyframes": n, "landmarks": info["landmarks"],
           "format_version": info["format_version"],
           "kB_per_keyframe": round(info["total_bytes"] / n / 1000, 1),
           "parts_kB_per_keyframe": {k: round(v / n / 1000, 1)
                                     for k, v in sorted(info["bytes"].items())}}
    if args.files:
        out["files_kB_per_keyframe"] = {
            k: round(v / n / 1000, 2)
            for k, v in sorted(file_sizes(Path(info["directory"])).items(), key=lambda kv: -kv[1])}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
