"""How long a freshly loaded engine takes to answer its first queries, and what of it goes to
the keyframe statistics (:mod:`reloc_service.algorithms.pose.map_consistency`) it computes
rather than reads from the snapshot: ``Engine.load`` time, each of the first N queries'
latency, the statistics computed and the seconds spent on them, each run in a fresh process,
medians over the runs.

    python scripts/first_answers_after_load.py build DATASET MAP_DIR
    python scripts/first_answers_after_load.py time DATASET MAP_DIR [--queries 3] [--runs 5]
        [--prepared]

``build`` makes the map of a reloc dataset (e.g. ``reloc synth --preset desk --out DATASET
--seed 0``) with the service's default method, trains it and saves it as ``reloc eval
--round-trip`` does (the service's default snapshot parts). ``time`` loads it in a new process
per run and answers the dataset's first queries (as a service worker runs them);
``--prepared`` waits for the whole-map pools the load makes before the first query, so that
the first answers' time is their own. Run ``time`` from another checkout (``PYTHONPATH``) to
compare: a snapshot saved without stored statistics computes them all.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

OPTIONS_FILE = "eval-options.json"


def build(dataset_dir: Path, map_dir: Path) -> None:
    from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
    from reloc_service.tools.data.dataset import read_dataset
    from reloc_service.tools.eval.backends import LandmarkSource
    from reloc_service.tools.eval.evaluate import (
        ground_truth_covariance,
        options_stating_dataset_calibration,
    )
    from reloc_service.tools.eval.inprocess import InProcessBackend

    dataset = read_dataset(dataset_dir)
    options = dict(options_stating_dataset_calibration({}, dataset) or {})
    backend = InProcessBackend([DEFAULT_METHOD], options, LandmarkSource.AUTO)
    exact = ground_truth_covariance((0.0, 0.0))   # ``reloc eval``'s default: exact poses
    for kf_id, entry in enumerate(dataset.map_entries):   # as ``reloc eval`` builds it
        backend.add_keyframe(kf_id, dataset.load_image(entry), dataset.camera(entry),
                             entry.world_from_cam, depth=dataset.load_depth(entry),
                             pose_covariance=exact)
    start = time.perf_counter()
    backend.train(progress=False)
    snapshot = backend.engine.save(map_dir, parts=backend._service.stored_parts())
    (map_dir / OPTIONS_FILE).write_text(json.dumps(options))
    print(f"trained in {time.perf_counter() - start:.2f} s, saved {snapshot}")
    backend.close()


def first_answers(dataset_dir: Path, map_dir: Path, queries: int, prepared: bool
                  ) -> dict[str, Any]:
    """One run, in this process: the load's and each first query's seconds, and the
    statistics computed (the calls of the computation, where this checkout has it)."""
    import numpy as np

    from reloc_service.algorithms.pose import map_consistency
    from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
    from reloc_service.algorithms.relocalizers.overlap import close_helpers
    from reloc_service.core.frame import Frame
    from reloc_service.engine import Engine
    from reloc_service.tools.data.dataset import read_dataset
    from reloc_service.tools.eval.backends import LandmarkSource
    from reloc_service.tools.eval.inprocess import as_a_service_worker, engine_conf

    computed, spent = [0], [0.0]
    name = "_computed" if hasattr(map_consistency, "_computed") else "_statistics"
    compute, statistics_of = getattr(map_consistency, name), map_consistency._statistics

    def counted(*args: Any, **kw: Any) -> Any:
        computed[0] += 1
        return compute(*args, **kw)

    def timed(*args: Any, **kw: Any) -> Any:
        start = time.perf_counter()
        try:
            return statistics_of(*args, **kw)
        finally:
            spent[0] += time.perf_counter() - start

    setattr(map_consistency, name, counted)
    if name != "_statistics":
        map_consistency._statistics = timed
    dataset = read_dataset(dataset_dir)
    options = json.loads((map_dir / OPTIONS_FILE).read_text())
    conf = engine_conf([DEFAULT_METHOD], options, LandmarkSource.AUTO)
    frames = [(dataset.load_image(e), dataset.camera(e)) for e in dataset.query_entries[:queries]]
    start = time.perf_counter()
    engine = Engine.load(map_dir, conf)
    load_s = time.perf_counter() - start
    if prepared:
        engine.prepared.wait()
    latencies = []
    with as_a_service_worker():
        for image, camera in frames:
            start = time.perf_counter()
            engine.relocalize(Frame(np.asarray(image), camera))
            latencies.append(time.perf_counter() - start)
    engine.close()
    close_helpers()
    return {"load_s": load_s, "query_s": latencies, "computed": computed[0],
            "statistics_s": spent[0] if name != "_statistics" else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("build", "time", "run"))
    parser.add_argument("dataset", type=Path)
    parser.add_argument("map_dir", type=Path)
    parser.add_argument("--queries", type=int, default=3)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--prepared", action="store_true")
    args = parser.parse_args()
    if args.command == "build":
        build(args.dataset, args.map_dir)
        return
    if args.command == "run":   # one run, for ``time``'s fresh process
        print(json.dumps(first_answers(args.dataset, args.map_dir, args.queries, args.prepared)))
        return
    rows = []
    for _ in range(args.runs):
        out = subprocess.run([sys.executable, __file__, "run", str(args.dataset),
                              str(args.map_dir), "--queries", str(args.queries)]
                             + (["--prepared"] if args.prepared else []),
                             capture_output=True, text=True, check=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        print(rows[-1])
    print(f"Engine.load median {statistics.median(r['load_s'] for r in rows) * 1e3:.1f} ms; "
          f"statistics computed {statistics.median(r['computed'] for r in rows):.0f}")
    for i in range(args.queries):
        print(f"query {i}: median {statistics.median(r['query_s'][i] for r in rows) * 1e3:.0f} ms")
    print(f"first {args.queries} together: median "
          f"{statistics.median(sum(r['query_s']) for r in rows) * 1e3:.0f} ms")


if __name__ == "__main__":
    main()
