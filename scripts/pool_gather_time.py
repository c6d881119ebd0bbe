"""How long a stored map's whole-map pools take to gather (each feature kind's
:meth:`LandmarkPool.gather_streamed` over every keyframe, in the map's order), in one
process, after numba's kernel is compiled: the median and every run, seconds.

    python scripts/pool_gather_time.py MAP_DIR [--runs 5]

MAP_DIR: a stored map's directory (``map`` in a fleet template,
W/fleet/template/template/map after ``reloc bench --only fleet --workdir W``).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from reloc_service.algorithms.pose.landmark_pool import LandmarkPool
from reloc_service.core.numeric import first_occurrences
from reloc_service.storage.snapshot import load_map


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map_dir", type=Path)
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    first_occurrences(np.arange(4, dtype=np.int64))   # compiled (or its cache read) first
    state, _ = load_map(args.map_dir)
    keyframes = list(state.keyframes.values())
    for kind in ("orb", "sift"):
        times = []
        for _ in range(args.runs):
            start = time.perf_counter()
            pool = LandmarkPool.gather_streamed(keyframes, kind)
            times.append(time.perf_counter() - start)
        print(f"{kind}: {len(pool.landmark_ids)} rows, median {statistics.median(times):.3f} s "
              f"({', '.join(f'{t:.3f}' for t in times)})")


if __name__ == "__main__":
    main()
