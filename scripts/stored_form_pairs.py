"""Recall of one trained map as each stored form restores it: build and train a dataset's map
once, then per mode save it as a service does (``Engine.save`` with the service's default
parts but the mode's descriptors and codec), load it (``Engine.load``), score every method,
and write one ``reloc eval`` JSON per mode (and print kB a keyframe per snapshot part).

    .venv/bin/python scripts/stored_form_pairs.py /work/data/repeated-hard /tmp/out/rh 0,0 \\
        landmarks:none per-landmark:none per-landmark:pq[:RATE] -- METHOD...

A mode is ``DESCRIPTORS:CODEC[:RATE][:KEY=VALUE...]``; RATE, the false-alarm rate of the
own-descriptor test of :mod:`reloc_service.storage.landmark_descriptors` (default its
``OWN_FALSE_ALARM``); KEY=VALUE, another field of ``StoredParts`` (``vocabulary=uint8``,
``landmark_points=float16``, ``landmark_budget=300``: digits read as an integer), or
``score=no`` to print the sizes only.
One build for every mode: the modes' answers differ by what they store alone."""

from __future__ import annotations

import sys
import tempfile
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

import reloc_service.storage.landmark_descriptors as ld
from reloc_service.engine import Engine
from reloc_service.service.config import ServiceSection
from reloc_service.tools.eval import evaluate as ev


def kb_per_part(snapshot_root: str, keyframes: int, unit: int = 1024) -> dict[str, float]:
    """Bytes a keyframe of each snapshot part in ``unit`` (1024: KiB, as this script has
    always reported; 1000: kB, as `reloc bench` and map_size_parts.py report), a model file
    hard-linked under several methods counted once."""
    sizes: dict[str, int] = {}
    seen: set[tuple[int, int]] = set()   # a model file equal to another method's: a hard link
    for f in Path(snapshot_root).rglob("*"):
        if f.is_file() and (f.stat().st_dev, f.stat().st_ino) not in seen:
            seen.add((f.stat().st_dev, f.stat().st_ino))
            rel = f.relative_to(snapshot_root).parts
            key = rel[2] if len(rel) > 3 else "other"
            if key == "features":
                key = "f:" + ".".join(rel[3].split(".")[:2]) if "descriptor" in rel[3] else "f:other"
            elif key == "landmarks":
                key = "l:points" if "points" in rel[3] else "l:other"
            sizes[key] = sizes.get(key, 0) + f.stat().st_size
    return {k: round(v / unit / max(keyframes, 1), 1) for k, v in sorted(sizes.items())}


def main(args: list[str]) -> None:
    root, prefix, sigma = args[0], args[1], tuple(float(v) for v in args[2].split(","))
    split = args.index("--")
    modes, methods = args[3:split], args[split + 1:]
    claimed, source = ev.QueryCamera(), ev.LandmarkSource("auto")
    truth_cov = ev.ground_truth_covariance(sigma)
    dataset = ev.read_dataset(root)
    ev._check_dataset(dataset, source)
    backend = ev._make_backend(methods, {}, source, None)
    build_s = ev._build_map(backend, dataset, source, False, truth_cov)
    train_s = ev._timed(lambda: backend.train(progress=False))
    trained = backend.engine
    base = ServiceSection().stored_parts()
    name = Path(root).name
    for mode in modes:
        descriptors, codec, *rest = mode.split(":")
        extra: dict[str, str | int] = {k: int(v) if v.isdigit() else v for k, v in
                                       (r.split("=", 1) for r in rest if "=" in r)}
        rate = [r for r in rest if "=" not in r]
        score = extra.pop("score", "yes") != "no"
        ld.own_rows.__kwdefaults__["rate"] = float(rate[0]) if rate else ld.OWN_FALSE_ALARM
        tmp = tempfile.TemporaryDirectory(prefix="reloc-pair-")
        trained.save(tmp.name, parts=replace(base, descriptors=descriptors,
                                             descriptor_codec=codec, **extra))
        parts = kb_per_part(tmp.name, len(trained.map.snapshot().keyframes))
        print(name, mode, "kB/kf", round(sum(parts.values()), 1), parts, flush=True)
        if not score:
            tmp.cleanup()
            continue
        backend.engine = Engine.load(tmp.name, trained.conf)
        with ev.as_a_service_worker():
            results = [ev._evaluate_method(backend, dataset, m, False, claimed, truth_cov)
                       for m in methods]
        info = ev._map_info(backend, dataset, source, build_s, train_s)
        ev.EvalResult(dataset=ev._dataset_info(dataset, claimed), map=info, methods=results,
                      machine=ev.machine_info(), backend=backend.description, options={},
                      created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
                      ground_truth_sigma=sigma).write_json(
                          f"{prefix}_{mode.replace(':', '_').replace('=', '-')}.json")
        for r in results:
            print(name, mode, r.method, f"{100 * r.summary.recall['5cm_5deg']:.1f}",
                  f"{100 * r.summary.wrong_rate:.1f}", flush=True)
        backend.engine.close()
        tmp.cleanup()


if __name__ == "__main__":
    main(sys.argv[1:])
