"""Which landmarks the relocalizers' answers rest on, ranked as a summary map ranks them
(:mod:`reloc_service.storage.landmark_summary`): build and train a dataset's map, answer its
queries with each method, and for every verified estimate take the best rank (over the
keyframes that see it) of each inlier landmark; print the rank quantiles and, per budget,
the share of inliers kept and of estimates that keep at least ``min_inliers`` of them.

    .venv/bin/python scripts/summary_inlier_ranks.py /work/data/room 0,0 -- METHOD...

A statistic of what answers use, from which a budget is chosen (docs/performance.md,
"A summary map")."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

import reloc_service.algorithms.relocalizers.base as reloc_base
from reloc_service.engine import Engine
from reloc_service.storage.landmark_summary import landmark_views, row_ranks
from reloc_service.tools.eval import evaluate as ev
from reloc_service.tools.eval.inprocess import InProcessBackend

BUDGETS = (100, 150, 200, 300, 400, 600, 800, 1000)


def best_ranks(engine: Engine) -> tuple[np.ndarray, np.ndarray]:
    """(ids, best rank) of every landmark: its best row rank over the keyframes seeing it."""
    state = engine.map.snapshot()
    columns = state.landmarks.columns()
    views = landmark_views(columns)
    best = np.full(len(columns.ids), np.iinfo(np.int64).max, np.int64)
    for kf in state.keyframes.values():
        for kind in kf.features:
            feats = kf.features[kind]
            rows = columns.rows(np.asarray(feats.landmark_ids, np.int64))
            has = np.flatnonzero(rows >= 0)
            ranks = row_ranks(np.asarray(feats.keypoints_px, np.float64)[has], views[rows[has]],
                              (kf.camera.width, kf.camera.height))
            np.minimum.at(best, rows[has], ranks)
    return np.asarray(columns.ids), best


def main(args: list[str]) -> None:
    root, (t_sigma, r_sigma) = args[0], (float(v) for v in args[1].split(","))
    sigma = (t_sigma, r_sigma)
    methods = args[args.index("--") + 1:]
    source, truth_cov = ev.LandmarkSource("auto"), ev.ground_truth_covariance(sigma)
    dataset = ev.read_dataset(root)
    ev._check_dataset(dataset, source)
    backend = ev._make_backend(methods, {}, source, None)
    assert isinstance(backend, InProcessBackend)   # no remote: the map is in this process
    ev._build_map(backend, dataset, source, False, truth_cov)
    backend.train(progress=False)
    ids, best = best_ranks(backend.engine)
    accepted: list[np.ndarray] = []
    verify = reloc_base.verify

    def recording(estimate: Any, conf: Any) -> tuple[bool, str, float]:
        """The verification's verdict; the inliers of an accepted estimate recorded."""
        ok, reason, confidence = verify(estimate, conf)
        if ok and estimate.inlier_landmark_ids is not None:
            accepted.append(np.asarray(estimate.inlier_landmark_ids, np.int64))
        return ok, reason, confidence

    reloc_base.verify = recording
    for method in methods:
        accepted.clear()
        with ev.as_a_service_worker():
            ev._evaluate_method(backend, dataset, method, False, ev.QueryCamera(), truth_cov)
        report(root, method, accepted, ids, best)


def report(root: str, method: str, accepted: list[np.ndarray], ids: np.ndarray,
           best: np.ndarray) -> None:
    if not accepted:
        print(root, method, "no verified estimate")
        return
    ranks = [best[np.searchsorted(ids, a)] for a in accepted]
    flat = np.concatenate(ranks)
    q = np.percentile(flat, [50, 90, 95, 99]).round().astype(int).tolist()
    counts = [len(r) for r in ranks]
    print(root, method, "estimates", len(ranks), "inliers median", int(np.median(counts)),
          "min", min(counts), "best-rank quantiles 50/90/95/99", q, flush=True)
    floor = reloc_base.VerifyConf().min_inliers
    for budget in BUDGETS:
        kept = [int((r < budget).sum()) for r in ranks]
        print(root, method, "budget", budget, "inliers kept", f"{(flat < budget).mean():.3f}",
              "estimates keeping >= min_inliers", f"{np.mean([k >= floor for k in kept]):.3f}",
              "min kept", min(kept), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
