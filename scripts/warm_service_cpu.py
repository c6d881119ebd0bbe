"""What a warm query costs the service beside its round trip: copies of a stored fleet
template, served first by a baseline ``reloc serve`` (one map, a budget no map reaches),
then by a fleet one (``max_resident_mb = 1000``: one map resident at a time), and the same
random picks (map, query image) sent to each twice in a row (the fleet's first send is a
cold load). For each send: the round trip, the service's CPU time and minor page faults
(``/proc/PID/stat`` before and after) and the CPU time of each of its threads that used any
(``/proc/PID/task``). Prints each pick, then the medians of the second sends and the median
over the picks of the fleet's round trip over the baseline's for the same pick.

    python scripts/warm_service_cpu.py T --maps 6 --picks 40 [--after-pools]

``--after-pools``: the fleet's second send waits until the service logs the map's SIFT pool
ready (the background pools of a loaded map made). T: a template a fleet run stored
(``reloc bench --only fleet --workdir W``: W/fleet/template/template).
"""

from __future__ import annotations

import argparse
import os
import random
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from reloc_service.tools.bench import fleet
from reloc_service.tools.bench.fleet_service import Served, first_answer, serve
from reloc_service.tools.bench.stored_map import CAMERA_ID, copies

#: Clock ticks per second of /proc's CPU times (Linux's USER_HZ).
TICKS = os.sysconf("SC_CLK_TCK")


def process_counters(pid: int) -> tuple[int, float]:
    """(minor page faults, CPU seconds) of process ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[7]), (int(fields[11]) + int(fields[12])) / TICKS


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds of each thread of process ``pid`` by thread id."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:   # ended meanwhile
            continue
        out[tid] = (int(fields[11]) + int(fields[12])) / TICKS
    return out


def send(client: Any, pid: int, jpeg: bytes) -> dict[str, Any]:
    """One query's round trip (ms), the service's CPU (ms), faults and busy threads."""
    threads, (faults, cpu) = thread_cpu(pid), process_counters(pid)
    start = time.perf_counter()
    result = client.relocalize(jpeg, camera_id=CAMERA_ID)
    ms = (time.perf_counter() - start) * 1000
    after, (faults2, cpu2) = thread_cpu(pid), process_counters(pid)
    busy = {t: round((c - threads.get(t, 0.0)) * 1000) for t, c in after.items()
            if c > threads.get(t, 0.0)}
    return {"ms": ms, "cpu_ms": (cpu2 - cpu) * 1000, "faults": faults2 - faults,
            "threads": busy, "method": result.method}


def pools_ready(served: Served) -> bool:
    """Whether every map the service loaded has logged its SIFT pool ready."""
    log = served.log.read_text(errors="replace")
    return log.count("sift pool of") >= log.count("orb pool of")


def run(label: str, served: Served, plan: list[tuple[str, int]], jpegs: list[bytes],
        after_pools: bool, timeout_s: float) -> list[dict[str, Any]]:
    from reloc_client.client import RelocClient

    rows = []
    with RelocClient(served.endpoint, map=plan[0][0], timeout=timeout_s) as client:
        for name, i in plan:
            client.map = name
            first = send(client, served.process.pid, jpegs[i])
            deadline = time.monotonic() + 10
            while after_pools and not pools_ready(served) and time.monotonic() < deadline:
                time.sleep(0.01)
            second = send(client, served.process.pid, jpegs[i])
            rows.append({"map": name, "image": i, "first": first, "second": second})
            print(label, name, i, {k: round(v) if isinstance(v, float) else v
                                   for k, v in second.items()}, flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("template", type=Path)
    parser.add_argument("--maps", type=int, default=6)
    parser.add_argument("--picks", type=int, default=40)
    parser.add_argument("--after-pools", action="store_true")
    parser.add_argument("--cache", type=Path, default=Path("out/bench-cache"),
                        help="where the fleet's scene is rendered (or found rendered)")
    args = parser.parse_args()
    conf = fleet.FleetConf(maps=args.maps, queries=args.picks)
    scene = fleet.render_scene(conf, args.cache)
    template, _ = fleet.reuse_template(args.template, scene)
    jpegs = scene.queries.jpegs
    names = [f"site{i:03d}" for i in range(conf.maps)]
    rng = random.Random(1)
    plan = [(rng.choice(names), rng.randrange(len(jpegs))) for _ in range(args.picks)]
    pixels = scene.camera.width * scene.camera.height
    found = {}
    with tempfile.TemporaryDirectory(prefix="reloc-warm-cpu-") as tmp:
        storage = Path(tmp) / "storage"
        copies(template, storage, names)
        for label, budget, picks in (("baseline", fleet.AMPLE_MB, [(names[0], i) for _, i in plan]),
                                     ("fleet", 1000.0, plan)):
            with serve(conf, storage, budget, Path(tmp) / label, pixels) as served:
                first_answer(served, names[0], jpegs[0], conf.startup_timeout_s)
                found[label] = run(label, served, picks, jpegs,
                                   args.after_pools and label == "fleet", conf.query_timeout_s)
    for label, rows in found.items():
        second = [r["second"] for r in rows]
        print(f"{label} second sends: round trip {np.median([s['ms'] for s in second]):.1f} ms, "
              f"service CPU {np.median([s['cpu_ms'] for s in second]):.0f} ms, "
              f"faults {np.median([s['faults'] for s in second]):.0f} (medians)")
    ratios = [f["second"]["ms"] / b["second"]["ms"]
              for f, b in zip(found["fleet"], found["baseline"], strict=True)]
    print(f"fleet over baseline, same pick: median {np.median(ratios):.2f}x "
          f"(quartiles {np.percentile(ratios, 25):.2f}-{np.percentile(ratios, 75):.2f})")


if __name__ == "__main__":
    main()
