"""Localization with a prior, measured: every query of each dataset answered by the default
method without a prior, with a good prior (its ground-truth pose perturbed by a draw from the
stated covariance: 5 cm and 2 deg, 1 sigma per axis, as a VIO gives it) and with a wrong one
(2 m or 30 deg off, the same small covariance stated: a VIO that drifted or reset).

Per set: p50 latency (relocalize from the decoded grey image, as ``reloc bench``'s accuracy
section times it) against the p50 of decode + ORB extraction (500 features, the fast path's)
of the same images, recall within 5 cm / 5 deg, wrong poses (beyond 0.5 m / 15 deg, ``reloc
eval``'s definition), the share answered by the tracking step; for wrong priors, the answers
within that threshold of the wrong prior.

    .venv/bin/python scripts/prior_tracking_bench.py /work/shared/data/real/* /work/data/room \\
        /tmp/data/stereo --json out/prior.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from reloc_service.algorithms.relocalizers.base import Prior
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.algorithms.relocalizers.tracking import TRACK
from reloc_service.core.features import FeatureConf, extract
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import pose_covariance_from_sigmas, pose_error, se3_exp
from reloc_service.tools.bench.accuracy import eval_default_landmarks
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval import evaluate as ev
from reloc_service.tools.eval.metrics import WRONG_THRESHOLD

SIGMA_M, SIGMA_DEG = 0.05, 2.0
RECALL = (0.05, 5.0)


def _good_prior(gt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    xi = np.concatenate([rng.normal(0, SIGMA_M, 3), rng.normal(0, np.deg2rad(SIGMA_DEG), 3)])
    return gt @ se3_exp(xi)


def _shifted(gt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    direction = rng.normal(size=3)
    out = gt.copy()
    out[:3, 3] += 2.0 * direction / np.linalg.norm(direction)
    return out


def _turned(gt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    axis = rng.normal(size=3)
    return gt @ se3_exp(np.concatenate([np.zeros(3), np.deg2rad(30.0) * axis
                                        / np.linalg.norm(axis)]))


def _limit_ms(path: Path) -> tuple[float, float]:
    """(decode + ORB 500, decode + ORB 1000) milliseconds of the image file at ``path``."""
    data = np.frombuffer(path.read_bytes(), np.uint8)
    out = []
    for n in (500, 1000):
        start = time.perf_counter()
        image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
        extract(image, FeatureConf(kind="orb", max_features=n))
        out.append((time.perf_counter() - start) * 1e3)
    return out[0], out[1]


def _row(records: list[dict[str, Any]]) -> dict[str, Any]:
    lat = [r["ms"] for r in records]
    ok = [r for r in records if r["ok"]]
    return {"n": len(records), "p50_ms": float(np.median(lat)) if lat else None,
            "answered": len(ok),
            "recall_5cm_5deg": float(np.mean([r["ok"] and r["t"] <= RECALL[0]
                                              and r["r"] <= RECALL[1] for r in records])),
            "wrong": sum(r["ok"] and (r["t"] > WRONG_THRESHOLD[0] or r["r"] > WRONG_THRESHOLD[1])
                         for r in records),
            "near_wrong_prior": sum(r.get("near_prior", False) for r in records),
            "by_track": sum(r["method"] == TRACK for r in records)}


def bench_set(root: Path, repeats: int, seed: int) -> dict[str, Any]:
    dataset = read_dataset(root)
    source = eval_default_landmarks()
    ev._check_dataset(dataset, source)
    backend = ev.InProcessBackend([DEFAULT_METHOD], {}, source)
    covariance = pose_covariance_from_sigmas(SIGMA_M, np.deg2rad(SIGMA_DEG))
    rng = np.random.default_rng(seed)
    runs: dict[str, list[dict[str, Any]]] = {"no prior": [], "prior 5cm/2deg": [],
                                             "prior 2 m off": [], "prior 30 deg off": []}
    limits: list[tuple[float, float]] = []
    try:
        ev._build_map(backend, dataset, source, False, ev.ground_truth_covariance((0.0, 0.0)))
        backend.train(progress=False)
        engine = backend.engine

        def ask(name: str, image: np.ndarray, camera: Any, gt: np.ndarray,
                prior_pose: np.ndarray | None) -> None:
            prior = None if prior_pose is None else Prior(prior_pose, covariance=covariance)
            start = time.perf_counter()
            result = engine.relocalize(Frame(image, camera), method=DEFAULT_METHOD, prior=prior)
            ms = (time.perf_counter() - start) * 1e3
            rec: dict[str, Any] = {"ok": result.ok, "ms": ms, "method": result.method,
                                   "t": np.inf, "r": np.inf}
            if result.ok:
                t, r = pose_error(result.world_from_cam, gt)
                rec["t"], rec["r"] = t, float(np.degrees(r))
                if prior_pose is not None and name.endswith("off"):
                    # Within the wrong-pose threshold of the wrong prior (2 m or 30 deg from
                    # the truth: the two neighbourhoods do not overlap).
                    t, r = pose_error(result.world_from_cam, prior_pose)
                    rec["near_prior"] = bool(t <= WRONG_THRESHOLD[0]
                                             and np.degrees(r) <= WRONG_THRESHOLD[1])
            runs[name].append(rec)

        for entry in dataset.query_entries:
            image, camera = dataset.load_image(entry), dataset.camera(entry)
            gt = np.array(entry.world_from_cam)
            limits.append(_limit_ms(dataset.root / entry.image_path))
            ask("no prior", image, camera, gt, None)
            for _ in range(repeats):
                ask("prior 5cm/2deg", image, camera, gt, _good_prior(gt, rng))
            ask("prior 2 m off", image, camera, gt, _shifted(gt, rng))
            ask("prior 30 deg off", image, camera, gt, _turned(gt, rng))
    finally:
        backend.close()
    lim = np.asarray(limits)
    orb500, orb1000 = float(np.median(lim[:, 0])), float(np.median(lim[:, 1]))
    rows = {name: _row(recs) for name, recs in runs.items()}
    for row in rows.values():
        row["over_limit"] = None if row["p50_ms"] is None else row["p50_ms"] / orb500
    return {"set": root.name, "queries": len(dataset.query_entries),
            "decode_orb500_p50_ms": orb500, "decode_orb1000_p50_ms": orb1000, "runs": rows}


def _table(results: list[dict[str, Any]]) -> list[str]:
    lines = ["| set | run | p50 ms | limit ms (decode+ORB 500) | ratio | recall 5cm/5deg | "
             "wrong | near wrong prior | by track |", "|---|---|---|---|---|---|---|---|---|"]
    for res in results:
        for name, row in res["runs"].items():
            lines.append(f"| {res['set']} | {name} | {row['p50_ms']:.1f} | "
                         f"{res['decode_orb500_p50_ms']:.1f} | {row['over_limit']:.2f} | "
                         f"{row['recall_5cm_5deg']:.0%} | {row['wrong']} | "
                         f"{row['near_wrong_prior']} | {row['by_track']}/{row['n']} |")
    return lines


def _markdown(results: list[dict[str, Any]], command: str, started: str,
              load: tuple[float, float, float]) -> list[str]:
    return ["## Localization with a prior", "",
            f"Generated by `{command}` ({started}, load average at the start "
            f"{', '.join(f'{v:.2f}' for v in load)}; not part of `reloc bench`'s run above). "
            f"Method `{DEFAULT_METHOD}` through `Engine.relocalize`, timed from the decoded grey "
            f"image; limit = p50 of JPEG/PNG decode + ORB extraction (500 features) of the same "
            f"images. Priors: the ground truth perturbed by a draw of the stated covariance "
            f"({SIGMA_M * 100:.0f} cm, {SIGMA_DEG:.0f} deg, 1 sigma per axis), or moved 2 m / "
            f"turned 30 deg (random direction) with the same covariance stated. Recall within "
            f"{RECALL[0] * 100:.0f} cm / {RECALL[1]:.0f} deg; wrong: returned beyond "
            f"{WRONG_THRESHOLD[0]} m / {WRONG_THRESHOLD[1]:.0f} deg; near wrong prior: returned "
            f"within the wrong-pose threshold of the wrong prior; by track: answers given by the tracking "
            f"step.", "", *_table(results)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", type=Path)
    parser.add_argument("--repeats", type=int, default=3,
                        help="good priors drawn per query (default 3)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--markdown", type=Path,
                        help="write the section for docs/performance.md")
    args = parser.parse_args(argv)
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    load = os.getloadavg()
    results = []
    for root in args.datasets:
        if not (root / "queries.txt").is_file():
            print(f"skipping {root}: no queries.txt", file=sys.stderr)
            continue
        results.append(bench_set(root, args.repeats, args.seed))
        print("\n".join(_table(results[-1:])[2:]), flush=True)
    print("\n".join(_table(results)))
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        command = " ".join(["scripts/prior_tracking_bench.py", *(argv or sys.argv[1:])])
        args.markdown.write_text("\n".join(_markdown(results, command, started, load)) + "\n")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"sigma_m": SIGMA_M, "sigma_deg": SIGMA_DEG,
                                         "method": DEFAULT_METHOD, "results": results},
                                        indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
