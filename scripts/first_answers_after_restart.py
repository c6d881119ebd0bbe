"""How fast a service answers right after a restart: a reloc dataset's map uploaded to a fresh
``reloc serve`` (worker processes, loopback), trained, the service stopped with SIGTERM, then
started again several times, each time its queries sent twice as soon as it serves the map,
and stopped. Prints each pass's latencies (ms; ``!`` a refusal, its reason printed).

    python scripts/first_answers_after_restart.py DATASET [--checkout DIR] [--restarts 3]
        [--port 47391] [--workdir DIR] [--workers 2] [--settle 6]

``--checkout`` is the reloc checkout (with its ``.venv``) whose ``reloc serve`` and
``reloc-client upload`` run, e.g. a clean clone of an older commit to compare with; the
queries are sent by this checkout's Python client. ``--settle``: seconds between a start and
the first query (the same for every code compared).
"""

from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

SERVICE_TOML = """[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{port}"]
multicast_scouting = false
[service]
instance = "restart-{port}"
storage = "{storage}"
workers = {workers}
opencv_threads = 1
allow_new_maps = true
worker_mode = "process"
"""


def _queries(dataset: Path) -> list[tuple[bytes, str]]:
    """(encoded image, camera id) of every line of ``dataset``'s queries.txt."""
    rows = [line.split() for line in (dataset / "queries.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    return [((dataset / row[0]).read_bytes(), row[1]) for row in rows]


def _start(reloc: Path, config: Path, log: Path, settle: float) -> subprocess.Popen[bytes]:
    with log.open("ab") as out:
        service = subprocess.Popen([str(reloc), "serve", "--config", str(config)],
                                   stdout=out, stderr=subprocess.STDOUT)
    time.sleep(settle)
    return service


def _stop(service: subprocess.Popen[bytes]) -> None:
    service.send_signal(signal.SIGTERM)
    service.wait(timeout=120)


def _passes(port: int, queries: list[tuple[bytes, str]], passes: int = 2
            ) -> list[list[tuple[float, bool]]]:
    """Each pass's (latency ms, answered) per query, through the Python client."""
    from reloc_client.client import RelocClient

    out = []
    with RelocClient(f"tcp/127.0.0.1:{port}", map="map", timeout=120) as client:
        for _ in range(passes):
            latencies = []
            for image, camera_id in queries:
                start = time.perf_counter()
                reply = client.relocalize(image, camera_id=camera_id)
                latencies.append(((time.perf_counter() - start) * 1e3, reply.ok))
                if not reply.ok:
                    print(f"  refused: {reply.reason[:200]}")
            out.append(latencies)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--checkout", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--restarts", type=int, default=3)
    parser.add_argument("--port", type=int, default=47391)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--settle", type=float, default=6.0)
    parser.add_argument("--workdir", type=Path, default=Path("out/first-answers-after-restart"))
    args = parser.parse_args()
    bin_dir = args.checkout / ".venv" / "bin"
    shutil.rmtree(args.workdir, ignore_errors=True)
    (args.workdir / "storage").mkdir(parents=True)
    config = args.workdir / "service.toml"
    config.write_text(SERVICE_TOML.format(port=args.port, storage=args.workdir / "storage",
                                          workers=args.workers))
    log = args.workdir / "serve.log"
    service = _start(bin_dir / "reloc", config, log, args.settle)
    try:
        subprocess.run([str(bin_dir / "reloc-client"), "-e", f"tcp/127.0.0.1:{args.port}",
                        "--map", "map", "--timeout", "300", "upload", str(args.dataset),
                        "--train", "--wait"], check=True, stdout=subprocess.DEVNULL)
    finally:
        _stop(service)
    queries = _queries(args.dataset)
    for restart in range(1, args.restarts + 1):
        service = _start(bin_dir / "reloc", config, log, args.settle)
        try:
            passes = _passes(args.port, queries)
        finally:
            _stop(service)
        shown = ["  ".join(f"{ms:.0f}{'' if ok else '!'}" for ms, ok in p) for p in passes]
        sums = [sum(ms for ms, _ in p) for p in passes]
        print(f"restart {restart}: first pass {shown[0]} | {sums[0]:.0f} ms; second pass "
              f"{sums[1]:.0f} ms")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
