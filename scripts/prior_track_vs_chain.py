"""Where localization with a prior answers worse than without: every query answered by the
default chain without a prior and by the tracking step alone (``"track"``) from the exact
ground truth and from ``--draws`` good priors (5 cm / 2 deg, 1 sigma per axis, stated in the
prior's covariance, as ``reloc bench --only prior`` draws them), on the map ``reloc eval``
builds. One line per query: each answer's error, its error in the query camera's frame
(x right, y down, z along the optical axis: which way the pose slid), the largest position
sigma it states, and the keyframes it matched; then the recall within 5 cm / 5 deg of both.

    .venv/bin/python scripts/prior_track_vs_chain.py ../shared/data/real/7scenes_redkitchen \\
        --keyframe-sigma 0.015,0.45 --json out/track_vs_chain.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from reloc_service.algorithms.relocalizers.base import Prior, RelocResult
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import invert, pose_covariance_from_sigmas, pose_error
from reloc_service.tools.bench import prior as prior_bench
from reloc_service.tools.bench.accuracy import eval_default_landmarks, service_default_method
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval import evaluate as ev


def describe(result: RelocResult, gt_world_from_cam: np.ndarray) -> dict[str, Any]:
    """One answer: ok, method, reason, inliers, keyframes; when answered, its error (cm,
    deg), its error in the ground-truth camera's frame (cm) and its largest stated position
    sigma (cm)."""
    out: dict[str, Any] = {"ok": result.ok, "method": result.method, "reason": result.reason,
                           "inliers": result.inliers, "keyframes": result.matched_keyframe_ids}
    if result.ok and result.world_from_cam is not None:
        t, r = pose_error(result.world_from_cam, gt_world_from_cam)
        gt_from_answer = invert(gt_world_from_cam) @ result.world_from_cam
        out.update(t_cm=100 * float(t), r_deg=float(np.degrees(r)),
                   cam_err_cm=[round(100 * float(x), 1) for x in gt_from_answer[:3, 3]])
        if result.covariance is not None:
            sigma = np.sqrt(np.linalg.eigvalsh(np.asarray(result.covariance)[:3, :3]).max())
            out["sigma_cm"] = 100 * float(sigma)
    return out


def within_recall(answer: dict[str, Any]) -> bool:
    return bool(answer["ok"] and answer["t_cm"] <= 100 * prior_bench.RECALL[0]
                and answer["r_deg"] <= prior_bench.RECALL[1])


def bench_setup(root: Path, seed: int) -> tuple[str, Any, Any, ev.InProcessBackend,
                                                np.ndarray, np.random.Generator]:
    """What both prior diagnostics start from, as ``reloc bench --only prior`` does: the
    service's default method, the dataset at ``root``, where its landmarks come from, an
    in-process backend to build its map, the good prior's covariance (5 cm, 2 deg) and the
    draws' generator."""
    method = service_default_method()
    dataset, source = read_dataset(root), eval_default_landmarks()
    backend = ev.InProcessBackend([method], {}, source)
    covariance = pose_covariance_from_sigmas(prior_bench.SIGMA_M,
                                             np.deg2rad(prior_bench.SIGMA_DEG))
    return method, dataset, source, backend, covariance, np.random.default_rng(seed)


def compare(root: Path, draws: int, seed: int, keyframe_sigma: tuple[float, float]
            ) -> list[dict[str, Any]]:
    method, dataset, source, backend, covariance, rng = bench_setup(root, seed)
    rows: list[dict[str, Any]] = []
    try:
        ev._build_map(backend, dataset, source, False, ev.ground_truth_covariance(keyframe_sigma))
        backend.train(progress=False)
        engine = backend.engine
        tracker = engine._live[method].tracker
        for q, entry in enumerate(dataset.query_entries):
            image, camera = dataset.load_image(entry), dataset.camera(entry)
            gt = np.array(entry.world_from_cam)
            priors = [gt] + [prior_bench.good_prior(gt, rng) for _ in range(draws)]
            row = {"query": q, "image": entry.image_path,
                   "chain": describe(engine.relocalize(Frame(image, camera), method=method), gt),
                   "track": [describe(tracker.relocalize(
                       Frame(image, camera), prior=Prior(p, covariance=covariance)), gt)
                       for p in priors]}
            rows.append(row)
            print(line(row), flush=True)
    finally:
        backend.close()
    return rows


def short(answer: dict[str, Any]) -> str:
    if not answer["ok"]:
        return f"-- {answer['reason'][:44]}"
    return (f"{answer['t_cm']:5.1f} cm {answer['r_deg']:4.2f} deg cam {answer['cam_err_cm']} "
            f"sigma {answer.get('sigma_cm', float('nan')):4.1f} kf {answer['keyframes'][:4]}")


def line(row: dict[str, Any]) -> str:
    track = " | ".join(short(a) for a in row["track"])
    return f"{row['query']:3d} chain {short(row['chain'])} || track (gt prior first) {track}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--draws", type=int, default=2, help="good priors per query")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--keyframe-sigma", metavar="T_M,R_DEG", default=None,
                        help="the keyframes' pose accuracy (default: the set's in reloc bench "
                             "--only prior, exact for a set it does not name)")
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)
    sigma = (tuple(float(v) for v in args.keyframe_sigma.split(",")) if args.keyframe_sigma
             else getattr(prior_bench, "KEYFRAME_SIGMAS", {}).get(args.dataset.name, (0.0, 0.0)))
    rows = compare(args.dataset, args.draws, args.seed, (sigma[0], sigma[1]))
    chain = np.mean([within_recall(r["chain"]) for r in rows])
    track = np.mean([within_recall(a) for r in rows for a in r["track"][1:]])
    answered = np.mean([a["ok"] for r in rows for a in r["track"][1:]])
    print(f"recall 5 cm / 5 deg: chain without prior {chain:.0%}; track alone with a good "
          f"prior {track:.0%} (answers {answered:.0%})")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
