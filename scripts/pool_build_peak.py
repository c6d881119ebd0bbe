"""What making a stored map's whole-map pools holds in memory: its pools' final size, and the
peak of this process's resident memory while they are made above what it holds once they
are (the heap's free pages given back): the rates per keyframe of
reloc_service/service/pool_reserve.py. What stays besides the pools (the keyframes'
features the pools read, built on first use) is counted with the map's usage already.

    python scripts/pool_build_peak.py MAP_DIR [--method METHOD]

MAP_DIR: a stored map's directory (``map`` in a fleet template,
W/fleet/template/template/map after ``reloc bench --only fleet --workdir W``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from reloc_service.algorithms.pose.map_pool import pool_bytes
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.algorithms.relocalizers.map_pools import restore_pools
from reloc_service.engine import Engine, EngineConf
from reloc_service.service.memory import rss_bytes, trim_now
from reloc_service.storage.snapshot import load_map
from reloc_service.storage.snapshot_format import model_dir_name
from reloc_service.tools.bench.fleet_memory import peak_during

MB = 1024 * 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map_dir", type=Path)
    parser.add_argument("--method", default=DEFAULT_METHOD)
    args = parser.parse_args()
    _, models_dir = load_map(args.map_dir)
    engine = Engine.load(args.map_dir, EngineConf(methods=(args.method,)), pools=False)
    state = engine.map.snapshot()
    relocalizer = engine.relocalizer(args.method)
    if relocalizer is None:
        raise SystemExit(f"{args.map_dir}: expected method {args.method} in the map's engine")
    keyframes = len(state.keyframes)
    directory = None if models_dir is None else models_dir / model_dir_name(args.method)
    start = time.perf_counter()
    before, peak, _ = peak_during(lambda: restore_pools(relocalizer, state, directory))
    seconds = time.perf_counter() - start
    held = pool_bytes(state)
    trim_now()
    after = rss_bytes()
    transient = peak - after
    print(f"{keyframes} keyframes, pools made in {seconds:.2f} s: they hold {held / MB:.1f} MB "
          f"({held / keyframes:.0f} B per keyframe); resident memory {before / MB:.1f} MB "
          f"before, peak {peak / MB:.1f} MB, {after / MB:.1f} MB after (the heap's free "
          f"pages given back); the making's peak above what stays: {transient / MB:.1f} MB "
          f"({transient / keyframes:.0f} B per keyframe, {transient / held:.3f} times the pools)")

if __name__ == "__main__":
    main()
