"""Where a tracked query's time goes: the bench's good priors (``reloc bench --only prior``'s
draws: seed, three per query, in its order) given to the default method, twice (the first
pass warms the compiled kernels and the tracker's kept local maps), and of the second pass's
queries that tracking answers, the CPU time of each step of the tracker (this thread's CPU
clock, less sensitive than the wall clock to a machine shared with other work): p50 and
mean in ms. ``--json`` writes every tracked query's stage times and every query's answer
(pose and covariance), so two versions of the code can be compared answer for answer.

    .venv/bin/python scripts/prior_track_stages.py /work/data/room --json out/stages_room.json

The steps are the functions :mod:`reloc_service.algorithms.relocalizers.tracking` calls,
timed by wrapping the names it holds (nothing else runs differently).
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from reloc_service.algorithms.relocalizers import tracking, tracking_local_map
from reloc_service.algorithms.relocalizers.base import Prior
from reloc_service.core import features as feature_lib
from reloc_service.core.frame import Frame
from reloc_service.tools.bench import prior as prior_bench
from reloc_service.tools.eval import evaluate as ev

sys.path.insert(0, str(Path(__file__).resolve().parent))
from prior_track_vs_chain import bench_setup  # noqa: E402  (a sibling script)

#: The names in ``tracking``'s namespace that are its steps.
STEPS = ("match_in_windows", "predict_windows", "pixel_sigmas", "background_distance",
         "solve_pnp_indexed", "grow", "widen_for_source_keyframes", "limit_focal_starts",
         "settle_pose_errors", "note_map_calibration", "result_from_estimate",
         "narrow_support")


class StageClock:
    """CPU ms per step of the query being tracked (:attr:`current`), and of every tracked
    query once :attr:`recording` is on (:attr:`tracked`)."""

    def __init__(self) -> None:
        self.current: dict[str, float] = {}
        self.tracked: list[dict[str, float]] = []
        self.recording = False

    def timed(self, label: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def run(*args: Any, **kwargs: Any) -> Any:
            start = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.current[label] = (self.current.get(label, 0.0)
                                       + (time.thread_time() - start) * 1e3)
        return run

    def install(self) -> None:
        for name in STEPS:
            setattr(tracking, name, self.timed(name, getattr(tracking, name)))
        feature_lib.extract = self.timed("features", feature_lib.extract)
        maps = tracking_local_map.LocalMaps
        maps.get = self.timed("local_map", maps.get)  # type: ignore[method-assign]
        relocalizer = tracking.TrackingRelocalizer
        for name in ("_within_prior", "_narrows"):
            setattr(relocalizer, name, self.timed(name.lstrip("_"), getattr(relocalizer, name)))
        track = relocalizer.relocalize

        @functools.wraps(track)
        def relocalize(inner: Any, *args: Any, **kwargs: Any) -> Any:
            self.current = {}
            result = self.timed("total", track)(inner, *args, **kwargs)
            if result.ok and self.recording:
                self.tracked.append(self.current)
            return result
        relocalizer.relocalize = relocalize  # type: ignore[method-assign,assignment]


def answers(engine: Any, method: str, queries: list[tuple[Any, ...]], covariance: np.ndarray
            ) -> list[dict[str, Any]]:
    """Every query answered with its prior: ok, method, pose and covariance."""
    out = []
    for image, camera, prior_pose in queries:
        result = engine.relocalize(Frame(image, camera), method=method,
                                   prior=Prior(prior_pose, covariance=covariance))
        out.append({"ok": result.ok, "method": result.method,
                    "world_from_cam": None if result.world_from_cam is None
                    else np.asarray(result.world_from_cam).tolist(),
                    "covariance": None if result.covariance is None
                    else np.asarray(result.covariance).tolist()})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--draws", type=int, default=3, help="good priors per query")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    method, dataset, source, backend, covariance, rng = bench_setup(args.dataset, args.seed)
    clock = StageClock()
    clock.install()
    try:
        sigma = prior_bench.KEYFRAME_SIGMAS.get(args.dataset.name, (0.0, 0.0))
        ev._build_map(backend, dataset, source, False, ev.ground_truth_covariance(sigma))
        backend.train(progress=False)
        queries = []
        for entry in dataset.query_entries:
            image, camera = dataset.load_image(entry), dataset.camera(entry)
            gt = np.array(entry.world_from_cam)
            queries += [(image, camera, prior_bench.good_prior(gt, rng))
                        for _ in range(args.draws)]
        answers(backend.engine, method, queries, covariance)    # warm-up pass
        clock.recording = True
        answered = answers(backend.engine, method, queries, covariance)
    finally:
        backend.close()
    print(f"{args.dataset.name}: {len(queries)} priors, {len(clock.tracked)} tracked; "
          "CPU ms of the tracked ones (p50, mean):")
    labels = sorted({k for row in clock.tracked for k in row},
                    key=lambda k: -float(np.median([r.get(k, 0.0) for r in clock.tracked])))
    for label in labels:
        values = [row.get(label, 0.0) for row in clock.tracked]
        print(f"  {label:28s} {np.median(values):7.2f} {np.mean(values):7.2f}")
    if args.json:
        args.json.write_text(json.dumps({"dataset": str(args.dataset), "stages": clock.tracked,
                                         "answers": answered}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
