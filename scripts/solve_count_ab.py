"""The ORB step (or the chain) with the first pool's solve skipped where it cannot be kept
(fewer matches than ``guided_below_inliers``) against main's path (always solved), query by
query on one map in one process, the order alternating so the machine's load hits both
alike: PnP solves per query, wall time, and whether every answer is the same (status,
reason, inliers, matches, pose, covariance and keyframes, bit for bit). Also the share of
the step's time spent on candidate groups heard after one verified (the uniqueness check's
cost) and how many of those the check then set aside as the same solution. With
``--early``, ``multi.duplicates_early`` on (the default) against off.

    .venv/bin/python scripts/solve_count_ab.py ../shared/data/real/7scenes_redkitchen \\
        --keyframe-sigma 0.015,0.45 --step 0 --repeats 2
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections import Counter
from pathlib import Path
from time import perf_counter
from typing import Any

import numpy as np

import reloc_service.algorithms.pose.keyframe_disagreement as keyframe_disagreement
import reloc_service.algorithms.pose.p3p as p3p
import reloc_service.algorithms.pose.repetition as repetition
import reloc_service.algorithms.relocalizers.multi as multi
import reloc_service.algorithms.relocalizers.solution_weighing as solution_weighing
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.core.frame import Frame
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval.backends import LandmarkSource
from reloc_service.tools.eval.evaluate import _build_map, ground_truth_covariance
from reloc_service.tools.eval.inprocess import InProcessBackend, as_a_service_worker

COUNT: Counter[str] = Counter()
P3P = p3p.P3PPoseFinder
MATCH_AND_SOLVE, FIND_DEFERRED = P3P._match_and_solve, P3P.find_pose_deferred
DUPLICATES = solution_weighing.SolutionWeighing._duplicates_a_solution
RESULT_FROM_ESTIMATE = multi.result_from_estimate


def counted(solve: Any) -> Any:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        COUNT["solves"] += 1
        return solve(*args, **kwargs)
    return wrapper


for module in (p3p, repetition, keyframe_disagreement):
    module.solve_pnp_indexed = counted(module.solve_pnp_indexed)  # type: ignore[attr-defined]


def use_skip(on: bool) -> None:
    """This branch's first-pool skip, or main's path (every first pool solved)."""
    def always_solved(self: Any, *args: Any, solve_from: int = 0, **kwargs: Any) -> Any:
        return MATCH_AND_SOLVE(self, *args, **kwargs)
    P3P._match_and_solve = MATCH_AND_SOLVE if on else always_solved  # type: ignore[method-assign]


def use_early(steps: list[Any], on: bool) -> None:
    """``multi.duplicates_early`` on or off in every multi step."""
    for step in steps:
        step.conf = dataclasses.replace(step.conf, duplicates_early=on)


def timed_find(self: Any, *args: Any, **kwargs: Any) -> Any:
    """find_pose_deferred, its time added to the groups heard after one verified."""
    start = perf_counter()
    found = FIND_DEFERRED(self, *args, **kwargs)
    COUNT["ms_after" if COUNT["verified_before"] else "ms_before"] += int(
        (perf_counter() - start) * 1e6)
    return found


def group_result(*args: Any, **kwargs: Any) -> Any:
    """multi's result_from_estimate, noting a candidate group that verified."""
    result = RESULT_FROM_ESTIMATE(*args, **kwargs)
    COUNT["verified_before"] |= bool(result.ok)
    return result


def duplicates(self: Any, query: Any, estimate: Any, earlier: list[Any], hypotheses: int) -> bool:
    same = DUPLICATES(self, query, estimate, earlier, hypotheses)
    COUNT["duplicates"] += same
    return same


def answer_key(result: Any) -> tuple[Any, ...]:
    def raw(a: Any) -> bytes | None:
        return None if a is None else np.asarray(a).tobytes()
    return (result.status, result.reason, result.inliers, result.num_matches,
            raw(result.world_from_cam), raw(result.covariance), tuple(result.matched_keyframe_ids))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--keyframe-sigma", default="0,0")
    parser.add_argument("--step", type=int, default=0, help="chain step index; -1: the chain")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--early", action="store_true",
                        help="compare multi.duplicates_early on against off")
    args = parser.parse_args(argv)
    sigma = tuple(float(v) for v in args.keyframe_sigma.split(","))
    dataset = read_dataset(args.dataset)
    backend = InProcessBackend([DEFAULT_METHOD], {}, LandmarkSource.AUTO)
    ms: dict[bool, list[float]] = {False: [], True: []}
    solves: dict[bool, list[int]] = {False: [], True: []}
    step_ms: list[float] = []
    after_ms: list[float] = []
    dups = same = total = 0
    try:
        _build_map(backend, dataset, LandmarkSource.AUTO, False,
                   ground_truth_covariance(sigma))  # type: ignore[arg-type]
        backend.train(progress=False)
        chain = backend.engine.relocalizer(DEFAULT_METHOD)
        step = chain if args.step < 0 else chain.steps[args.step]  # type: ignore[attr-defined]
        steps = [s for s in getattr(chain, "steps", [chain]) if hasattr(s.conf, "duplicates_early")]
        steps = steps if args.step < 0 else [step]
        configured = [s.conf for s in steps]
        P3P.find_pose_deferred = timed_find  # type: ignore[method-assign]
        multi.result_from_estimate = group_result
        solution_weighing.SolutionWeighing._duplicates_a_solution = duplicates  # type: ignore[method-assign]
        with as_a_service_worker():
            images = [(dataset.load_image(e), dataset.camera(e)) for e in dataset.query_entries]
            step.relocalize(Frame(*images[0]))
            for rep in range(args.repeats):
                for q, (image, camera) in enumerate(images):
                    got = {}
                    for on in ((False, True) if (q + rep) % 2 == 0 else (True, False)):
                        if args.early:
                            use_early(steps, on)
                        else:
                            use_skip(on)
                        COUNT.clear()
                        frame = Frame(image, camera)
                        start = perf_counter()
                        got[on] = answer_key(step.relocalize(frame))
                        ms[on].append((perf_counter() - start) * 1e3)
                        solves[on].append(COUNT["solves"])
                        if on:
                            step_ms.append(ms[on][-1])
                            after_ms.append(COUNT["ms_after"] / 1e3)
                            dups += COUNT["duplicates"]
                    total += 1
                    same += got[False] == got[True]
    finally:
        use_skip(True)
        if args.early:  # each step's own setting back (on, the default, unless configured)
            for s, conf in zip(steps, configured, strict=True):
                s.conf = conf
        P3P.find_pose_deferred = FIND_DEFERRED  # type: ignore[method-assign]
        multi.result_from_estimate = RESULT_FROM_ESTIMATE
        solution_weighing.SolutionWeighing._duplicates_a_solution = DUPLICATES  # type: ignore[method-assign]
        backend.close()
    label = "chain" if args.step < 0 else step.method
    print(f"{args.dataset.name} {label}: {total} queries x repeats, same answer {same}")
    names = (("duplicates_early off", "duplicates_early on") if args.early
             else ("main (always solved)", "skip"))
    for on, name in zip((False, True), names, strict=True):
        print(f"  {name}: solves per query mean {np.mean(solves[on]):.2f} "
              f"(total {sum(solves[on])}), p50 {np.median(ms[on]):.1f} ms, "
              f"mean {np.mean(ms[on]):.1f} ms")
    ratio = np.array(ms[True]) / np.array(ms[False])
    print(f"  median per-query ratio {names[1]} / {names[0]} {np.median(ratio):.3f}")
    print(f"  groups heard after a verified one: {np.sum(after_ms) / np.sum(step_ms):.0%} of "
          f"{names[1]}'s time", end="")
    # duplicates_early asks the same test of the poses it stops at: counted there too.
    print("" if args.early else f"; duplicates set aside {dups} (in {total} queries)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
