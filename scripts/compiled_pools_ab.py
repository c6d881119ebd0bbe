"""The default chain (or one of its steps) with guided matching's keypoint grid and the pools'
compiled first rows against main's paths (the KD-tree for every window, ``np.unique``'s sort),
query by query on one map in one process, the order alternating, so the machine's load hits
both alike: wall time of the step and whether every answer is the same (status, reason,
inliers, matches, pose, covariance and keyframes, bit for bit).

    .venv/bin/python scripts/compiled_pools_ab.py ../shared/data/real/7scenes_redkitchen \\
        --keyframe-sigma 0.015,0.45 --step 0 --repeats 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from time import perf_counter
from typing import Any

import numpy as np

import reloc_service.algorithms.pose.keypoint_grid as keypoint_grid
import reloc_service.core.numeric as numeric
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.core.frame import Frame
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval.backends import LandmarkSource
from reloc_service.tools.eval.evaluate import _build_map, ground_truth_covariance
from reloc_service.tools.eval.inprocess import InProcessBackend, as_a_service_worker

GRID, HASHED = keypoint_grid.compiled, numeric._first_occurrence_kernel


def use_compiled(on: bool) -> None:
    """The two compiled paths on, or both off (main's KD-tree windows and sorted unique)."""
    keypoint_grid.compiled = GRID if on else (lambda: None)  # type: ignore[assignment]
    numeric._first_occurrence_kernel = HASHED if on else (lambda: None)  # type: ignore[assignment]


def answer_key(result: Any) -> tuple[Any, ...]:
    def raw(a: Any) -> bytes | None:
        return None if a is None else np.asarray(a).tobytes()
    return (result.status, result.reason, result.inliers, result.num_matches,
            raw(result.world_from_cam), raw(result.covariance), tuple(result.matched_keyframe_ids))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--keyframe-sigma", default="0,0")
    parser.add_argument("--step", type=int, default=-1, help="chain step index; -1: the chain")
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args(argv)
    sigma = tuple(float(v) for v in args.keyframe_sigma.split(","))
    dataset = read_dataset(args.dataset)
    backend = InProcessBackend([DEFAULT_METHOD], {}, LandmarkSource.AUTO)
    ms: dict[bool, list[float]] = {False: [], True: []}
    same = total = 0
    try:
        _build_map(backend, dataset, LandmarkSource.AUTO, False,
                   ground_truth_covariance(sigma))  # type: ignore[arg-type]
        backend.train(progress=False)
        chain = backend.engine.relocalizer(DEFAULT_METHOD)
        step = chain if args.step < 0 else chain.steps[args.step]  # type: ignore[attr-defined]
        with as_a_service_worker():
            images = [(dataset.load_image(e), dataset.camera(e)) for e in dataset.query_entries]
            step.relocalize(Frame(*images[0]))
            for rep in range(args.repeats):
                for q, (image, camera) in enumerate(images):
                    got = {}
                    for on in ((False, True) if (q + rep) % 2 == 0 else (True, False)):
                        use_compiled(on)
                        frame = Frame(image, camera)
                        start = perf_counter()
                        got[on] = answer_key(step.relocalize(frame))
                        ms[on].append((perf_counter() - start) * 1e3)
                    total += 1
                    same += got[False] == got[True]
    finally:
        use_compiled(True)
        backend.close()
    label = "chain" if args.step < 0 else step.method
    print(f"{args.dataset.name} {label}: {total} queries x repeats, same answer {same}")
    for on, name in ((False, "main's paths"), (True, "compiled")):
        print(f"  {name}: p50 {np.median(ms[on]):.1f} ms, mean {np.mean(ms[on]):.1f} ms")
    ratio = np.array(ms[True]) / np.array(ms[False])
    print(f"  median per-query ratio compiled / main's {np.median(ratio):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
