"""Recall and stored size of one map as each vocabulary size trains it: build a dataset's map
once, then per ``[bow] leaf_descriptors`` value (0: today's fixed tree) re-train every method
on that map, save it as a service does (``Engine.save``, the service's default parts) and
print kB a keyframe per snapshot part and the bow tree's branching and leaves, score every
method on the trained engine, and write one ``reloc eval`` JSON per value.

    .venv/bin/python scripts/vocabulary_sizing.py /work/data/room-hard /tmp/out/rh 0,0 \\
        0 20 -- "sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p" bow+p3p

One build for every value: the answers differ by the vocabulary alone (training is seeded,
so value 0 re-trains today's tree)."""

from __future__ import annotations

import sys
import tempfile
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from stored_form_pairs import kb_per_part  # scripts/ is sys.path[0] when run as a script

from reloc_service.algorithms.place.bow import BagOfWords
from reloc_service.engine import Engine
from reloc_service.service.config import ServiceSection
from reloc_service.tools.eval import evaluate as ev


def bow_trees(engine: Engine, methods: list[str]) -> list[str]:
    """``branching^depth -> leaves`` of every trained bow place finder of ``methods``."""
    out = []
    for method in methods:
        reloc: Any = engine.relocalizer(method)
        for step in getattr(reloc, "steps", [reloc]):
            place = getattr(step, "place", None)
            if isinstance(place, BagOfWords) and place.vocabulary is not None:
                tree = place.vocabulary
                out.append(f"{tree.branching}^{tree.depth}->{tree.n_words}")
    return out


def main(args: list[str]) -> None:
    root, prefix, sigma = args[0], args[1], tuple(float(v) for v in args[2].split(","))
    split = args.index("--")
    values, methods = [int(v) for v in args[3:split]], args[split + 1:]
    claimed, source = ev.QueryCamera(), ev.LandmarkSource("auto")
    truth_cov = ev.ground_truth_covariance(sigma)
    dataset = ev.read_dataset(root)
    ev._check_dataset(dataset, source)
    backend = ev._make_backend(methods, {}, source, None)
    build_s = ev._build_map(backend, dataset, source, False, truth_cov)
    engine = backend.engine
    base_options = dict(engine.conf.options)
    name = Path(root).name
    for value in values:
        engine.conf = replace(engine.conf, options={**base_options,
                                                    "bow": {"leaf_descriptors": value}})
        train_s = ev._timed(lambda: engine.train())
        with tempfile.TemporaryDirectory(prefix="reloc-voc-") as tmp:
            engine.save(tmp, parts=ServiceSection().stored_parts())
            parts = kb_per_part(tmp, len(engine.map.snapshot().keyframes), unit=1000)
        print(name, value, "trees", bow_trees(engine, methods), "kB/kf",
              round(sum(parts.values()), 1), parts, flush=True)
        with ev.as_a_service_worker():
            results = [ev._evaluate_method(backend, dataset, m, False, claimed, truth_cov)
                       for m in methods]
        info = ev._map_info(backend, dataset, source, build_s, train_s)
        ev.EvalResult(dataset=ev._dataset_info(dataset, claimed), map=info, methods=results,
                      machine=ev.machine_info(), backend=backend.description,
                      options={"bow": {"leaf_descriptors": value}},
                      created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
                      ground_truth_sigma=sigma).write_json(f"{prefix}_leaf{value}.json")
        for r in results:
            print(name, value, r.method, f"{100 * r.summary.recall['5cm_5deg']:.1f}",
                  f"{100 * r.summary.wrong_rate:.1f}", flush=True)
    backend.close()


if __name__ == "__main__":
    main(sys.argv[1:])
