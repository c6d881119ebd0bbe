"""Time and peak resident memory of each query, in order, on a stored fleet template map:
``Engine.load`` of the map, then the fleet scene's queries by index (repeat one to see a warm
query after a cold one). The repetition check's whole-map pools are made by the first query
of each feature kind that reaches it.

    python scripts/big_map_queries.py build DIR          # the 1000-keyframe fleet template
    python scripts/big_map_queries.py query DIR OUT.json 0,1,1,7,3

``build`` stores it as ``reloc bench --only fleet`` does (DIR/template/template, reusable as
``--fleet-template``); ``query`` writes {load_s, queries: [{q, s, rss_peak_mb, ...}]}.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class Peak:
    """The largest resident size seen, sampled every 20 ms on a thread."""

    def __init__(self) -> None:
        self.peak, self.stop = rss_mb(), False

    def run(self) -> None:
        while not self.stop:
            self.peak = max(self.peak, rss_mb())
            time.sleep(0.02)


def main() -> None:
    from reloc_service.core.frame import Frame
    from reloc_service.core.geometry import pose_error
    from reloc_service.engine import Engine, EngineConf, MappingConf
    from reloc_service.tools.bench.fleet import FleetConf, build_template, render_scene

    cmd, work = sys.argv[1], Path(sys.argv[2])
    conf = FleetConf(maps=1, keyframes=1000)
    scene = render_scene(conf, work / "cache")
    if cmd == "build":
        _, info = build_template(conf, scene, work, print)
        print(json.dumps(info, default=str))
        return
    cv2.setNumThreads(1)
    start = time.perf_counter()
    engine = Engine.load(work / "template" / "template" / "map",
                         EngineConf(methods=(conf.method,),
                                    mapping=MappingConf(feature_kinds=("sift", "orb"))))
    out: dict = {"load_s": time.perf_counter() - start, "queries": []}
    for j in [int(a) for a in sys.argv[4].split(",")]:
        image = cv2.imdecode(np.frombuffer(scene.queries.jpegs[j], np.uint8),
                             cv2.IMREAD_GRAYSCALE)
        peak = Peak()
        sampler = threading.Thread(target=peak.run, daemon=True)
        sampler.start()
        t = time.perf_counter()
        result = engine.relocalize(Frame(image, scene.queries.camera))
        seconds = time.perf_counter() - t
        peak.stop = True
        sampler.join()
        err = None if result.world_from_cam is None else [
            float(e) for e in pose_error(np.asarray(result.world_from_cam), scene.queries.gts[j])]
        out["queries"].append({"q": j, "s": seconds, "rss_peak_mb": peak.peak,
                               "method": result.method, "ok": result.ok, "err_m_rad": err})
        print(out["queries"][-1], flush=True)
    Path(sys.argv[3]).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
