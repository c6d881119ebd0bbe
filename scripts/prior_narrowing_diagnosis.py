"""Why tracked poses go to the chain: every good prior ``reloc bench --only prior`` draws
(the same draws, seed and order) given to the tracking step alone (``"track"``), and for
each verified tracked pose at the narrowing test: its error (cm, deg, and in the camera
frame), the largest variance ratio to the prior's covariance
(:func:`~reloc_service.algorithms.pose.prior_gain.largest_variance_ratio`) of several of
its covariances (the decision's, the one the answer states without the keyframes' part,
the measurement's alone with the intrinsics exact, with the calibration's prior), the
direction of the largest ratio, the 6-dof Mahalanobis length of its error under each, and
the tracker's stage times. One JSON row per draw.

    .venv/bin/python scripts/prior_narrowing_diagnosis.py \\
        ../shared/data/real/strecha_fountain_p11 --json out/narrowing_fountain.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from reloc_service.algorithms.pose.base import PoseEstimate
from reloc_service.algorithms.pose.intrinsics_power import blind_spot_factor, governing_covariance
from reloc_service.algorithms.pose.prior_gain import largest_variance_ratio
from reloc_service.algorithms.relocalizers import tracking
from reloc_service.algorithms.relocalizers.base import (
    Prior,
    VerifyConf,
    note_map_calibration,
    stated_covariance,
)
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import invert, pose_error, se3_log
from reloc_service.tools.bench import prior as prior_bench
from reloc_service.tools.eval import evaluate as ev

sys.path.insert(0, str(Path(__file__).resolve().parent))
from prior_track_vs_chain import bench_setup  # noqa: E402  (a sibling script)

AXES = ("x", "y", "z", "rx", "ry", "rz")


def _direction(answer: np.ndarray, prior: np.ndarray) -> str:
    """The pose axis the largest generalised eigenvector of (answer, prior) leans on most,
    with its share of the (prior-whitened) direction."""
    chol = np.linalg.cholesky(prior)
    white = np.linalg.solve(chol, np.linalg.solve(chol, answer).T)
    vals, vecs = np.linalg.eigh(0.5 * (white + white.T))
    u = np.linalg.solve(chol.T, vecs[:, -1])
    u = u / np.linalg.norm(u)
    k = int(np.argmax(np.abs(u)))
    return f"{AXES[k]}:{abs(u[k]):.2f}"


def _mahalanobis(xi: np.ndarray, cov: np.ndarray | None) -> float | None:
    if cov is None:
        return None
    return float(np.sqrt(xi @ np.linalg.solve(cov, xi)))


def _parts(est: PoseEstimate) -> dict[str, np.ndarray]:
    """The covariances of ``est`` compared: the decision's (``covariance``), and where the
    intrinsics test passed, the measurement's (``d C``, intrinsics exact) and with the
    test's calibration prior (``d C + B P B^T``)."""
    out = {"decision": np.asarray(est.covariance)}
    check, given = est.intrinsics, est.covariance_given_intrinsics
    if check is not None and given is not None:
        shift = check.pose_shift
        out["given_calibration"] = np.asarray(given)
        out["measurement"] = np.asarray(given - shift @ check.prior.covariance @ shift.T)
        # The intrinsics' parts of the decision's covariance, each alone
        # (:func:`..map_consistency.covariance_with_intrinsics`).
        widening = (blind_spot_factor(check) - 1.0) * governing_covariance(check)
        for name, part in (("focal_prior", check.prior.covariance),
                           ("focal_data", check.covariance), ("focal_blind", widening),
                           ("focal_estimate", np.outer(check.theta, check.theta))):
            out[name] = np.asarray(shift @ part @ shift.T) + 1e-12 * np.eye(6)
        far = check.unexcluded_twist
        out["far"] = np.outer(far, far) + 1e-12 * np.eye(6)
        out["cal_match"] = np.eye(6) * 0 + est.covariance - out["focal_prior"]
    return out


def diagnose(root: Path, repeats: int, seed: int, keyframe_sigma: tuple[float, float],
             track_options: dict[str, Any], with_chain: bool = False
             ) -> list[dict[str, Any]]:
    method, dataset, source, backend, covariance, rng = bench_setup(root, seed)
    seen: dict[str, Any] = {}
    real_narrows = tracking.TrackingRelocalizer._narrows
    real_result = tracking.result_from_estimate

    def narrows(self, query, est, *args):  # type: ignore[no-untyped-def]
        seen["est"] = est
        seen["narrows"] = real_narrows(self, query, est, *args)
        return seen["narrows"]

    def result(est, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen["result"] = real_result(est, *args, **kwargs)
        return seen["result"]

    tracking.TrackingRelocalizer._narrows = narrows  # type: ignore[method-assign]
    tracking.result_from_estimate = result  # type: ignore[assignment]
    rows: list[dict[str, Any]] = []
    try:
        ev._build_map(backend, dataset, source, False, ev.ground_truth_covariance(keyframe_sigma))
        backend.train(progress=False)
        tracker = backend.engine._live[method].tracker
        tracker.conf = dataclasses.replace(tracker.conf, **track_options)
        for q, entry in enumerate(dataset.query_entries):
            image, camera = dataset.load_image(entry), dataset.camera(entry)
            gt = np.array(entry.world_from_cam)
            priors = [prior_bench.good_prior(gt, rng) for _ in range(repeats)]
            prior_bench.shifted_prior(gt, rng), prior_bench.turned_prior(gt, rng)
            chain = None
            if with_chain:
                answer = backend.engine.relocalize(Frame(image, camera), method=method)
                chain = {"ok": answer.ok, "method": answer.method}
                if answer.ok and answer.world_from_cam is not None:
                    t, r = pose_error(answer.world_from_cam, gt)
                    chain.update(t_cm=100 * t, r_deg=float(np.degrees(r)), inliers=answer.inliers)
                    if answer.covariance is not None:
                        chain["ratio_stated"] = largest_variance_ratio(
                            np.asarray(answer.covariance), covariance)
                print(f"{q:3d} chain without a prior: {chain}", flush=True)
            for d, pose in enumerate(priors):
                seen.clear()
                start = time.perf_counter()
                res = tracker.relocalize(Frame(image, camera),
                                         prior=Prior(pose, covariance=covariance))
                row = {"query": q, "draw": d, "ok": res.ok, "reason": res.reason,
                       "ms": 1e3 * (time.perf_counter() - start),
                       "timings_ms": {k: round(1e3 * v, 2) for k, v in res.timings.items()},
                       "chain": chain}
                est, stated = seen.get("est"), seen.get("result")
                if est is not None and stated is not None and stated.world_from_cam is not None:
                    t, r = pose_error(stated.world_from_cam, gt)
                    xi = se3_log(invert(stated.world_from_cam) @ gt)
                    row.update(tested=True, narrows=seen["narrows"], inliers=est.inliers,
                               t_cm=100 * t, r_deg=float(np.degrees(r)),
                               cam_err_cm=[round(100 * float(x), 2) for x in xi[:3]])
                    parts = _parts(est)
                    # What the answer would state had it noted, as the chain's steps do,
                    # whether the query claims the map's calibration.
                    noted = dataclasses.replace(est)
                    note_map_calibration(noted, camera, backend.engine.map.snapshot())
                    row["same_camera"] = noted.query_camera_is_map_calibration
                    cal = stated_covariance(noted, VerifyConf().max_position_sigma_m)
                    if cal is not None:
                        row["maha_stated_noted"] = _mahalanobis(xi, cal)
                        if noted.map_covariance is not None:
                            cal = cal - noted.map_covariance
                        parts["stated_noted_own"] = cal
                        if est.intrinsics is not None:
                            far = est.intrinsics.unexcluded_twist
                            parts["trusted_unique"] = cal + np.outer(far, far)
                    if stated.covariance is not None:
                        own = np.asarray(stated.covariance)
                        if est.map_covariance is not None:
                            own = own - est.map_covariance
                        parts["stated_own"] = own
                        row["maha_stated"] = _mahalanobis(xi, np.asarray(stated.covariance))
                    for name, cov in parts.items():
                        row[f"ratio_{name}"] = largest_variance_ratio(cov, covariance)
                        row[f"dir_{name}"] = _direction(cov, covariance)
                        row[f"maha_{name}"] = _mahalanobis(xi, cov)
                        row[f"sigma_z_cm_{name}"] = 100 * float(np.sqrt(cov[2, 2]))
                rows.append(row)
                print(line(row), flush=True)
    finally:
        tracking.TrackingRelocalizer._narrows = real_narrows  # type: ignore[method-assign]
        tracking.result_from_estimate = real_result  # type: ignore[assignment]
        backend.close()
    return rows


def line(row: dict[str, Any]) -> str:
    head = f"{row['query']:3d}.{row['draw']} {row['ms']:6.1f} ms"
    if not row.get("tested"):
        return f"{head} -- {row['reason'][:70]}"
    ratios = " ".join(f"{k[6:]}={row[k]:.2f}" for k in row if k.startswith("ratio_"))
    return (f"{head} {'track' if row['ok'] else 'chain'} {row['t_cm']:5.1f} cm "
            f"{row['r_deg']:4.2f} deg cam {row['cam_err_cm']} maha_dec "
            f"{row.get('maha_decision', float('nan')):.1f} maha_st "
            f"{row.get('maha_stated') or float('nan'):.1f} | {ratios}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--repeats", type=int, default=3, help="good priors per query")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write the rows here")
    parser.add_argument("--track", action="append", default=[], metavar="KEY=JSON",
                        help="a [track] option for this run, e.g. fallback='\"sift-half\"'")
    parser.add_argument("--chain", action="store_true",
                        help="also answer each query without a prior (the default method)")
    args = parser.parse_args(argv)
    options = {k: json.loads(v) for k, v in (o.split("=", 1) for o in args.track)}
    sigma = prior_bench.KEYFRAME_SIGMAS.get(args.dataset.name, (0.0, 0.0))
    rows = diagnose(args.dataset, args.repeats, args.seed, sigma, options, args.chain)
    tested = [r for r in rows if r.get("tested")]
    print(f"{len(rows)} draws, {len(tested)} verified to the narrowing test, "
          f"{sum(r['ok'] for r in rows)} tracked")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
