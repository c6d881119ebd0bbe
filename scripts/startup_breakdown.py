"""Where a ``reloc serve``'s start-up to its first answer goes: ``--maps`` copies of one map
(a fleet template, ``reloc bench --only fleet --workdir W`` keeps it in
W/fleet/template/template; the copies' snapshot files hard-linked) in a storage served with a
memory budget (so a map is loaded by its first query, as at a fleet's start), one query on the
last map sent as soon as the service answers.

    python scripts/startup_breakdown.py TEMPLATE_DIR QUERY_IMAGE [--runs 3] [--maps 200]
        [--mode process] [--compiled]

Prints, per run, seconds from the process start to: the service's first log line (its
imports), the storage scanned, the maps declared, its "serving" log line (Zenoh open), the
start of the map's cold load (the query arrived), its end, the first whole-map pool made
(the first step's), and the first answer, and the CPU seconds the service process used by
then (less sensitive to the machine's load than the times); then their medians, and the
load average.

``--compiled`` first compiles reloc_service's and reloc_client's modules to bytecode (in their
``__pycache__``, as ``pip install`` does for an installed package): where
PYTHONDONTWRITEBYTECODE is set, an editable install compiles them (1.6 MB of source) at every
start. The bytecode stays: delete the ``__pycache__`` folders to measure that again.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import re
import statistics
import tempfile
import time
from pathlib import Path

import cv2

from reloc_service.service.config import LimitsConf
from reloc_service.tools.bench.fleet import FleetConf
from reloc_service.tools.bench.fleet_service import compile_bytecode, first_answer, serve
from reloc_service.tools.bench.stored_map import StoredMap, copies

_STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")


def _stamp_of(log: Path, needle: str) -> float | None:
    """Wall-clock seconds of the first log line holding ``needle`` ("": the first line)."""
    for line in log.read_text(errors="replace").splitlines():
        m = _STAMP.match(line)
        if m and needle in line:
            return dt.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
    return None


def _cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system) process ``pid`` has used so far (its own threads, not
    its child processes); None where /proc is not there."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def one_run(template: Path, jpeg: bytes, work: Path, mode: str, maps: int
            ) -> dict[str, float | None]:
    storage = work / "storage"
    names = [f"site{i:03d}" for i in range(maps)]
    copies(StoredMap(template, 0, 0), storage, names)
    conf = FleetConf(maps=maps, worker_mode=mode)
    # an ample budget and the service's default image size limit
    with serve(conf, storage, 100000.0, work / "service",
               LimitsConf().max_image_pixels) as served:
        wall_start = time.time() - (time.monotonic() - served.started)
        total = first_answer(served, names[-1], jpeg, 300.0)
        cpu = _cpu_seconds(served.process.pid)
        stamps = {"first_log_s": _stamp_of(served.log, ""),
                  "scanned_s": _stamp_of(served.log, "maps found in"),
                  "declared_s": _stamp_of(served.log, "maps declared in"),
                  "serving_s": _stamp_of(served.log, "reloc service"),
                  "load_start_s": _stamp_of(served.log, ": loading,"),
                  "loaded_s": _stamp_of(served.log, "loaded on demand"),
                  "first_pool_s": _stamp_of(served.log, "pool of")}
    return {**{k: None if v is None else v - wall_start for k, v in stamps.items()},
            "first_answer_s": total, "service_cpu_s": cpu}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("template", type=Path)
    parser.add_argument("query", type=Path)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--maps", type=int, default=1,
                        help="copies of the template served (default: 1); the last is queried")
    parser.add_argument("--mode", choices=("thread", "process"), default="thread",
                        help="[service] worker_mode (default: thread, as the fleet bench)")
    parser.add_argument("--compiled", action="store_true",
                        help="compile the packages to bytecode first (see the docstring)")
    args = parser.parse_args()
    if args.compiled:
        compile_bytecode()
    image = cv2.imread(str(args.query), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"{args.query}: expected an image file")
    jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    runs = []
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory(prefix="startup-") as tmp:
            runs.append(one_run(args.template, jpeg, Path(tmp), args.mode, args.maps))
        print({k: None if v is None else round(v, 2) for k, v in runs[-1].items()})
    for key in runs[0]:
        values = [r[key] for r in runs if r[key] is not None]
        if values:
            print(f"median {key}: {statistics.median(values):.2f}")
    print("load average:", " ".join(f"{x:.1f}" for x in os.getloadavg()))


if __name__ == "__main__":
    main()
