"""How a map's queries right after its cold load compare with the same queries a few seconds
later, when its whole-map pools are made: copies of a stored fleet template served by one
``reloc serve`` with ``max_resident_mb = 1000`` (two maps resident), each picked in turn and
one query sent seven times: at once (cold: loaded on demand), twice more at once, then after
3 s, at once, after 3 s, at once. Prints each pick's round trips (ms) and the median per
position.

    python scripts/warm_after_load.py T --maps 3 --picks 9

T: a template a fleet run stored (``reloc bench --only fleet --workdir W``:
W/fleet/template/template); the copies go to a temporary folder, removed afterwards.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from reloc_service.tools.bench import fleet
from reloc_service.tools.bench.fleet_service import first_answer, serve
from reloc_service.tools.bench.stored_map import CAMERA_ID, copies

#: Seconds before each of the seven sends of a pick's query.
DELAYS_S = (0.0, 0.0, 0.0, 3.0, 0.0, 3.0, 0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("template", type=Path)
    parser.add_argument("--maps", type=int, default=3)
    parser.add_argument("--picks", type=int, default=9)
    parser.add_argument("--cache", type=Path, default=Path("out/bench-cache"),
                        help="where the fleet's scene is rendered (or found rendered)")
    args = parser.parse_args()
    from reloc_client.client import RelocClient

    conf = fleet.FleetConf(maps=args.maps, queries=args.picks)
    scene = fleet.render_scene(conf, args.cache)
    template, _ = fleet.reuse_template(args.template, scene)
    queries = scene.queries
    names = [f"site{i:03d}" for i in range(conf.maps)]
    rows = []
    with tempfile.TemporaryDirectory(prefix="reloc-warm-") as tmp:
        storage = Path(tmp) / "storage"
        copies(template, storage, names)
        with serve(conf, storage, 1000.0, Path(tmp) / "service",
                   scene.camera.width * scene.camera.height) as served:
            first_answer(served, names[0], queries.jpegs[0], conf.startup_timeout_s)
            with RelocClient(served.endpoint, map=names[0], timeout=conf.query_timeout_s) as c:
                for k in range(conf.queries):
                    c.map, i = names[k % len(names)], k % len(queries)
                    times = []
                    for delay in DELAYS_S:
                        time.sleep(delay)
                        start = time.perf_counter()
                        result = c.relocalize(queries.jpegs[i], camera_id=CAMERA_ID)
                        times.append(round((time.perf_counter() - start) * 1000, 1))
                    rows.append(times)
                    print(c.map, i, result.method, times, flush=True)
    print("median per position (cold, at once, at once, after 3 s, at once, after 3 s, "
          "at once):", np.median(np.array(rows), axis=0).round(1).tolist())


if __name__ == "__main__":
    main()
