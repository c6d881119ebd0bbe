"""Many stored maps, one ``reloc serve`` with a memory budget (``[service] max_resident_mb``):
start-up to the first answer, resident memory against the budget, and the latency of warm
queries (map resident) against cold ones (map loaded for the query), for queries spread over
every map at random; the same storage served with ``max_resident_mb = 0`` (every map restored
at start, today's default) for comparison. JSON on stdout.

    python scripts/many_maps.py [--maps 50] [--resident 5] [--queries 200] [--seed 0]
                                [--worker-mode thread|process]

Each map is a copy of one map of the tests' synthetic room (320x240, 6 keyframes, camera
cam0, trained, in a snapshot), built once in-process; ``--resident`` sets the budget to that
many maps' counted bytes (their quota usage).
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from conftest import PINHOLE, make_scene  # noqa: E402
from reloc_client.client import NoReplyError, RelocClient, ServiceBusy  # noqa: E402
from service_support import Events, endpoint, free_port, service_conf  # noqa: E402

from reloc_service.service.app import Service  # noqa: E402
from reloc_service.service.durability import MAP_NAME_FILE, map_dirname  # noqa: E402

METHOD = "sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p"
MB = 1024 * 1024


def build_template(root: Path, scene) -> tuple[Path, int]:
    """One stored map (trained, in a snapshot) and the bytes it counts."""
    storage = root / "template"
    port = free_port()
    def conf(port: int):
        return service_conf(port, storage, methods=[METHOD], default_method=METHOD,
                            worker_mode="thread", snapshot_every=0, train_on_load=False)

    service = Service(conf(port)).start()
    try:
        with RelocClient(endpoint(port), map="template", timeout=60) as client:
            events = Events(client)
            client.set_camera("cam0", scene.camera)
            events.wait("camera_added", id="cam0")
            for kf_id, (image, pose) in enumerate(zip(scene.keyframe_images,
                                                      scene.keyframe_poses, strict=True)):
                client.add_keyframe(kf_id, image, pose, camera_id="cam0")
            for kf_id in range(len(scene.keyframe_images)):
                events.wait("keyframe_added", id=kf_id, timeout=120)
            assert client.train(wait=True, timeout=300).accepted
            events.close()
    finally:
        service.stop()
    restored = Service(conf(free_port())).start()   # counted as a map loaded from its snapshot counts
    try:
        usage = restored.maps["template"].usage.total
    finally:
        restored.stop()
    return storage / "template", usage


def copies(template: Path, storage: Path, n: int) -> list[str]:
    names = [f"site{i:03d}" for i in range(n)]
    for name in names:
        target = storage / map_dirname(name)
        shutil.copytree(template, target, ignore=shutil.ignore_patterns("*.lock", "LOCK"))
        (target / MAP_NAME_FILE).write_text(name)
    return names


def write_config(path: Path, port: int, storage: Path, budget_mb: float,
                 worker_mode: str) -> Path:
    path.write_text("\n".join([
        "[zenoh]", 'mode = "peer"', f'listen = ["{endpoint(port)}"]',
        "multicast_scouting = false", "[service]", 'instance = "bench"',
        f'storage = "{storage}"', f'worker_mode = "{worker_mode}"', "workers = 2",
        f'methods = ["{METHOD}"]', f'default_method = "{METHOD}"',
        f"max_resident_mb = {budget_mb}", "cold_load_wait_s = 10.0",
        "[quotas]", "max_maps = 100000", "max_total_bytes = 1099511627776"]) + "\n")
    return path


def rss_mb(pid: int) -> float:
    """Resident memory of ``pid`` and its descendants (worker processes, their forkserver)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        todo += children.get(p, [])
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024
        except OSError:
            continue
    return total


def first_answer(port: int, name: str, scene, proc: subprocess.Popen, start: float) -> float:
    """Seconds from the process start to the first answered relocalize on ``name``."""
    while True:
        assert proc.poll() is None, "reloc serve exited"
        try:
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                result = client.relocalize(scene.query_images[0], camera_id="cam0")
                assert result.ok, result.reason
                return time.monotonic() - start
        except (ConnectionError, NoReplyError, ServiceBusy):
            time.sleep(0.05)


def run(storage: Path, names: list[str], scene, budget_mb: float, queries: int,
        seed: int, work: Path, worker_mode: str) -> dict[str, object]:
    port = free_port()
    config = write_config(work / f"serve-{budget_mb:g}.toml", port, storage, budget_mb,
                          worker_mode)
    log = (work / f"serve-{budget_mb:g}.log").open("ab")
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                             "--config", str(config)], cwd=REPO, stdout=log, stderr=log)
    rng = random.Random(seed)
    try:
        startup = first_answer(port, rng.choice(names), scene, proc, start)
        first_rss = rss_mb(proc.pid)
        clients = {n: RelocClient(endpoint(port), map=n, timeout=60) for n in names}
        warm, cold, busy, failed, peak = [], [], 0, 0, rss_mb(proc.pid)
        for _ in range(queries):
            name = rng.choice(names)
            client = clients[name]
            resident = client.status().resident
            t0 = time.perf_counter()
            for _attempt in range(5):   # busy: retry as the hint says
                try:
                    result = client.relocalize(scene.query_images[rng.randrange(3)],
                                               camera_id="cam0")
                    break
                except ServiceBusy:
                    busy += 1
                    time.sleep(1.0)
            failed += not result.ok
            (warm if resident else cold).append(time.perf_counter() - t0)
            peak = max(peak, rss_mb(proc.pid))
        resident_maps = sum(c.status().resident for c in clients.values())
        for client in clients.values():
            client.close()
    finally:
        proc.terminate()
        proc.wait(60)
        log.close()

    def pct(values: list[float], q: float) -> float | None:
        return None if not values else round(float(np.percentile(values, q)) * 1000, 1)

    return {"max_resident_mb": budget_mb, "startup_to_first_answer_s": round(startup, 2),
            "queries": queries, "not_ok": failed, "busy_replies": busy,
            "warm": len(warm), "cold": len(cold),
            "warm_p50_ms": pct(warm, 50), "warm_p99_ms": pct(warm, 99),
            "cold_p50_ms": pct(cold, 50), "cold_p99_ms": pct(cold, 99),
            "resident_maps_at_end": resident_maps, "rss_at_first_answer_mb": round(first_rss, 1),
            "peak_rss_mb": round(peak, 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--maps", type=int, default=50)
    parser.add_argument("--resident", type=int, default=5,
                        help="the budget: this many maps' counted bytes")
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--worker-mode", choices=("thread", "process"), default="thread")
    args = parser.parse_args()
    scene = make_scene(PINHOLE)
    with tempfile.TemporaryDirectory(prefix="reloc-many-maps-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        template, map_bytes = build_template(work, scene)
        built = time.perf_counter() - t0
        storage = work / "storage"
        names = copies(template, storage, args.maps)
        budget_mb = round(args.resident * map_bytes / MB + 0.01, 2)
        out = {"maps": args.maps, "map_counted_mb": round(map_bytes / MB, 3),
               "worker_mode": args.worker_mode, "template_build_s": round(built, 1),
               "bounded": run(storage, names, scene, budget_mb, args.queries, args.seed, work,
                              args.worker_mode),
               "all_resident": run(storage, names, scene, 0, args.queries, args.seed, work,
                                   args.worker_mode)}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
