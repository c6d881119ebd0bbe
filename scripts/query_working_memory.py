"""What a query holds in memory while it is answered, beyond what the process holds between
queries: a stored map loaded with its pools made, then each of the fleet scene's queries
(JPEG decoded, default method) answered alone with the heap trimmed before it, then one
image of no map's scene (a random texture, same size: every step of the method runs and none
verifies), and the peak of the process's resident memory during each (sampled every 2 ms)
above what it held before. ``--scales``: the random texture again at those multiples of
the camera's width and height (its camera scaled alike), two textures each: what the
largest image a service accepts may hold.
Prints each query's step and peak, and their median and max (MB).

    python scripts/query_working_memory.py T [--cache DIR] [--scales 1 1.5 2]

T: a template a fleet run stored (``reloc bench --only fleet --workdir W``:
W/fleet/template/template); its map is read in place, not changed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from reloc_client.result import RelocResult

from reloc_service.core.frame import Frame
from reloc_service.engine import Engine
from reloc_service.tools.bench import fleet
from reloc_service.tools.bench.fleet_memory import peak_during
from reloc_service.tools.bench.samples import decode_jpeg, random_texture_jpeg

MB = 1024 * 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("template", type=Path)
    parser.add_argument("--cache", type=Path, default=Path("out/bench-cache"),
                        help="where the fleet's scene is rendered (or found rendered)")
    parser.add_argument("--scales", type=float, nargs="*", default=[],
                        help="the random texture at these multiples of the camera's size too")
    args = parser.parse_args()
    conf = fleet.FleetConf()
    scene = fleet.render_scene(conf, args.cache)
    engine = Engine.load(args.template / "map")
    engine.prepared.wait()
    try:
        for jpeg in scene.queries.jpegs[:2]:   # the first answers' one-off work, not counted
            engine.relocalize(Frame(decode_jpeg(jpeg), scene.camera))
        steps = []
        texture = random_texture_jpeg(scene.camera.width, scene.camera.height)
        for i, jpeg in enumerate([*scene.queries.jpegs, texture]):
            def answer(jpeg: bytes = jpeg) -> RelocResult:
                return engine.relocalize(Frame(decode_jpeg(jpeg), scene.camera))

            before, peak, result = peak_during(answer)
            steps.append(peak - before)
            print(f"query {i}: {result.status.name} by {result.method}: "
                  f"{(peak - before) / MB:.1f} MB above {before / MB:.1f} MB")
        print(f"{len(steps)} queries: working memory median {np.median(steps) / MB:.1f} MB, "
              f"max {max(steps) / MB:.1f} MB")
        for scale in args.scales:
            camera = scene.camera.scaled(scale)
            for seed in (0, 1):
                texture = random_texture_jpeg(camera.width, camera.height, seed)

                def refused(jpeg: bytes = texture, camera: object = camera) -> RelocResult:
                    return engine.relocalize(Frame(decode_jpeg(jpeg), camera))  # type: ignore[arg-type]

                before, peak, result = peak_during(refused)
                print(f"random texture {camera.width}x{camera.height} ({seed}): "
                      f"{result.status.name}: {(peak - before) / MB:.1f} MB")
    finally:
        engine.close()


if __name__ == "__main__":
    main()
