"""Where a ``reloc serve``'s start-up to its first answer goes: one map stored in a storage
(a fleet template, ``reloc bench --only fleet --workdir W`` keeps it in
W/fleet/template/template) served with a memory budget (so it is loaded by the first query,
as at a fleet's start), one query sent as soon as the service answers.

    python scripts/startup_breakdown.py TEMPLATE_DIR QUERY_IMAGE [--runs 3] [--mode process]

Prints, per run, seconds from the process start to: the service's first log line (its
imports), its "serving" log line (Zenoh open), the end of the map's cold load, the first
whole-map pool made (the first step's), and the first answer; then their medians.
"""

from __future__ import annotations

import argparse
import datetime as dt
import re
import statistics
import tempfile
import time
from pathlib import Path

import cv2

from reloc_service.tools.bench.fleet import FleetConf
from reloc_service.tools.bench.fleet_service import first_answer, serve
from reloc_service.tools.bench.stored_map import StoredMap, copy_map

_STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")


def _stamp_of(log: Path, needle: str) -> float | None:
    """Wall-clock seconds of the first log line holding ``needle`` ("": the first line)."""
    for line in log.read_text(errors="replace").splitlines():
        m = _STAMP.match(line)
        if m and needle in line:
            return dt.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
    return None


def one_run(template: Path, jpeg: bytes, work: Path, mode: str) -> dict[str, float | None]:
    storage = work / "storage"
    copy_map(StoredMap(template, 0, 0), storage, "site000")
    conf = FleetConf(maps=1, worker_mode=mode)
    with serve(conf, storage, 100000.0, work / "service") as served:
        wall_start = time.time() - (time.monotonic() - served.started)
        total = first_answer(served, "site000", jpeg, 300.0)
        stamps = {"first_log_s": _stamp_of(served.log, ""),
                  "serving_s": _stamp_of(served.log, "reloc service"),
                  "loaded_s": _stamp_of(served.log, "loaded on demand"),
                  "first_pool_s": _stamp_of(served.log, "pool of")}
    return {**{k: None if v is None else v - wall_start for k, v in stamps.items()},
            "first_answer_s": total}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("template", type=Path)
    parser.add_argument("query", type=Path)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--mode", choices=("thread", "process"), default="thread",
                        help="[service] worker_mode (default: thread, as the fleet bench)")
    args = parser.parse_args()
    image = cv2.imread(str(args.query), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"{args.query}: expected an image file")
    jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    runs = []
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory(prefix="startup-") as tmp:
            runs.append(one_run(args.template, jpeg, Path(tmp), args.mode))
        print({k: None if v is None else round(v, 2) for k, v in runs[-1].items()})
    for key in runs[0]:
        values = [r[key] for r in runs if r[key] is not None]
        if values:
            print(f"median {key}: {statistics.median(values):.2f}")


if __name__ == "__main__":
    main()
