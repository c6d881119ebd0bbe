"""Whether a fleet service's memory budget holds under the costliest queries: copies of a
stored fleet template served with ``max_resident_mb = 1000`` (two thread workers), two clients
sending queries at once to maps picked at random (so maps are loaded, their pools made and
closed meanwhile), every second query, or with ``--all-garbage`` every one, an image of no
map's scene (a random texture: the default method runs every step on it, full-size SIFT
included, and refuses it). The service's RSS is sampled every 20 ms.
Prints the budget's parts as the service logged them, the answers, and the RSS p50 and max
against the budget.

    python scripts/worst_query_stream.py T [--maps 20] [--queries 40] [--all-garbage]

T: a template a fleet run stored (``reloc bench --only fleet --workdir W``:
W/fleet/template/template); the copies go to a temporary folder, removed afterwards.
"""

from __future__ import annotations

import argparse
import random
import re
import tempfile
import threading
from pathlib import Path

import numpy as np

from reloc_service.tools.bench import fleet
from reloc_service.tools.bench.fleet_memory import RssSampler
from reloc_service.tools.bench.fleet_service import Served, first_answer, serve
from reloc_service.tools.bench.samples import random_texture_jpeg
from reloc_service.tools.bench.stored_map import CAMERA_ID, copies

BUDGET_MB = 1000.0
TEXTURES = 8


def send(served: Served, names: list[str], images: list[bytes], garbage: list[bytes],
         queries: int, all_garbage: bool, seed: int, tally: dict[tuple[str, str], int],
         lock: threading.Lock) -> None:
    """One client's queries, counted in ``tally`` by (image kind, answer)."""
    from reloc_client.client import RelocClient

    rng = random.Random(seed)
    with RelocClient(served.endpoint, map=names[0], timeout=120) as client:
        for k in range(queries):
            client.map = rng.choice(names)
            refused = all_garbage or k % 2 == 1
            jpeg = rng.choice(garbage) if refused else rng.choice(images)
            try:
                answer = client.relocalize(jpeg, camera_id=CAMERA_ID).status.name
            except Exception as exc:   # counted, not fatal: the stream goes on
                answer = type(exc).__name__
            with lock:
                key = ("no map's scene" if refused else "a map's scene", answer)
                tally[key] = tally.get(key, 0) + 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("template", type=Path)
    parser.add_argument("--maps", type=int, default=20)
    parser.add_argument("--queries", type=int, default=40, help="per client")
    parser.add_argument("--all-garbage", action="store_true")
    parser.add_argument("--cache", type=Path, default=Path("out/bench-cache"),
                        help="where the fleet's scene is rendered (or found rendered)")
    args = parser.parse_args()

    conf = fleet.FleetConf(maps=args.maps)
    scene = fleet.render_scene(conf, args.cache)
    template, _ = fleet.reuse_template(args.template, scene)
    camera = scene.camera
    garbage = [random_texture_jpeg(camera.width, camera.height, seed) for seed in range(TEXTURES)]
    names = [f"site{i:03d}" for i in range(args.maps)]
    tally: dict[tuple[str, str], int] = {}
    lock = threading.Lock()
    with tempfile.TemporaryDirectory(prefix="reloc-worst-") as tmp:
        storage = Path(tmp) / "storage"
        copies(template, storage, names)
        with serve(conf, storage, BUDGET_MB, Path(tmp) / "service",
                   camera.width * camera.height) as served:
            first_answer(served, names[0], scene.queries.jpegs[0], conf.startup_timeout_s)
            sampler = RssSampler(served.process.pid, 0.02)
            with sampler.running():
                clients = [threading.Thread(target=send, args=(
                    served, names, scene.queries.jpegs, garbage, args.queries,
                    args.all_garbage, seed, tally, lock)) for seed in (1, 2)]
                for client in clients:
                    client.start()
                for client in clients:
                    client.join()
            budget = re.findall(r"memory budget .*", served.log.read_text())
    print(budget[-1] if budget else "no budget logged")
    print("answers:", ", ".join(f"{kind}: {answer} {n}" for (kind, answer), n in
                                sorted(tally.items())))
    rss = np.array([v for _, v in sampler.samples if v > 0])
    print(f"RSS of the service ({len(rss)} samples): p50 {np.median(rss):.0f} MB, max "
          f"{rss.max():.0f} MB ({rss.max() / BUDGET_MB:.2f}x the budget), "
          f"{(rss > BUDGET_MB).mean() * 100:.1f} % of the samples over it")


if __name__ == "__main__":
    main()
