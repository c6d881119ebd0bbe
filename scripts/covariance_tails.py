"""Where the default method's answers beyond 3 sigma come from (docs/covariance_tails.md).

    python scripts/covariance_tails.py table EVAL.json... [--plot PNG]
    python scripts/covariance_tails.py landmarks SYNTH_SET [--out JSON]
    python scripts/covariance_tails.py scales BEFORE_DIR AFTER_DIR [--plot PNG]
    python scripts/covariance_tails.py provenance SYNTH_SET

``table`` reads ``reloc eval`` JSON files (the first method of each) and prints, per set and
pooled, the median cov scale, the second-moment scale ``sqrt(mean d^2 / 3)`` and the share
beyond 3 sigma, fits a multivariate Student t to the pooled Mahalanobis lengths (maximum
likelihood over the degrees of freedom and the scale: ``d^2 / 3`` is F(3, nu) times the
scale) and, with ``--plot``, draws their quantiles against chi(3)'s and the fitted t's.

``landmarks`` evaluates a synthetic set (ground-truth depth) with the default method in this
process and, for every answer, solves its pose again from the same inliers (the PnP
refinement of :mod:`reloc_service.algorithms.pose.pnp`, from the answer) twice: on the map's
landmark points and on their ground-truth points (the first observation's pixel lifted with
the keyframe's true depth). Where the answers beyond 3 sigma come close to the truth on the
true points, the tail is the map's landmark errors, not the query's keypoints. It also
relocalizes every keyframe on its landmarks re-triangulated without it
(:func:`~reloc_service.algorithms.pose.held_out.held_out_points`, as the intrinsics
dispersion does) and scores the position error against its known pose under the PnP model
covariance: whether the map's own keyframes show the same tail.

``provenance`` builds a synthetic set's map as ``reloc eval`` does (default method) and tells
where its landmark errors were made: each landmark's error against its ground-truth point
when it was created (its first observation's pixel lifted with the keyframe's true depth) and
at the end, whether track refinement moved it, its stated depth sigma and observations at
creation; then, per pose a chain step verified (an answer, or a contender a later step
weighed), how many of its inlier landmarks are more than 30 cm off.

``scales`` compares two directories of ``reloc eval`` JSON files set by set (the files both
hold, by name): cov scale, second-moment scale and the share beyond 3 sigma before and after,
and with ``--plot`` both cov scales per set on a log axis against the 0.67-1.5 band.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

CHI3_MEDIAN = math.sqrt(stats.chi2.ppf(0.5, 3))


def _lengths(path: str) -> np.ndarray:
    queries = json.loads(Path(path).read_text())["methods"][0]["queries"]
    return np.array([q["t_err_mahalanobis"] for q in queries
                     if q["returned"] and q.get("t_err_mahalanobis") is not None], np.float64)


def _row(name: str, d: np.ndarray) -> str:
    return (f"| {name} | {len(d)} | {np.median(d) / CHI3_MEDIAN:.2f} | "
            f"{math.sqrt(np.mean(d**2) / 3):.2f} | {int((d > 3).sum())} ({100 * np.mean(d > 3):.1f} %) |")


def fit_t(d: np.ndarray) -> tuple[float, float]:
    """(nu, scale) of the multivariate t whose ``d^2 / 3 / scale`` is F(3, nu), by maximum
    likelihood over a grid (nu up to 200: a Gaussian at the top)."""
    best = (-math.inf, math.nan, math.nan)
    for nu in (2.5, 3, 3.5, 4, 5, 6, 8, 10, 15, 20, 30, 50, 200):
        for scale in np.linspace(0.3, 3.0, 271):
            ll = float(stats.f.logpdf(d**2 / 3 / scale, 3, nu).sum() - len(d) * math.log(scale))
            if ll > best[0]:
                best = (ll, float(nu), float(scale))
    return best[1], best[2]


def table(paths: list[str], plot: str | None) -> None:
    print("| set | answers | cov scale (median) | second-moment scale | beyond 3 sigma |")
    print("|---|---|---|---|---|")
    pooled = []
    for p in paths:
        d = _lengths(p)
        pooled.append(d)
        print(_row(Path(p).stem, d))
    d = np.concatenate(pooled)
    print(_row("all", d))
    nu, scale = fit_t(d)
    print(f"pooled: Gaussian beyond 3 sigma {100 * stats.chi2.sf(9, 3):.1f} %; fitted t: "
          f"nu {nu:g}, scale {scale:.2f} (its beyond 3 sigma "
          f"{100 * stats.f.sf(3 / scale, 3, nu):.1f} %)")
    if plot:
        _qq_plot(d, nu, scale, plot, len(paths))


def scales(before: str, after: str, plot: str | None) -> None:
    names = sorted({p.stem for p in Path(before).glob("*.json")}
                   & {p.stem for p in Path(after).glob("*.json")})
    print("| set | answers | cov scale | second-moment scale | beyond 3 sigma |")
    print("|---|---|---|---|---|")
    rows = []
    for name in names:
        b, a = _lengths(f"{before}/{name}.json"), _lengths(f"{after}/{name}.json")
        rows.append((name, np.median(b) / CHI3_MEDIAN, np.median(a) / CHI3_MEDIAN))
        print(f"| {name} | {len(b)} -> {len(a)} | {rows[-1][1]:.2f} -> {rows[-1][2]:.2f} | "
              f"{math.sqrt(np.mean(b**2) / 3):.2f} -> {math.sqrt(np.mean(a**2) / 3):.2f} | "
              f"{100 * np.mean(b > 3):.1f} % -> {100 * np.mean(a > 3):.1f} % |")
    if plot:
        _scales_plot(rows, plot)


def _scales_plot(rows: list[tuple[str, float, float]], out: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 0.45 * len(rows) + 1.2))
    y = np.arange(len(rows))
    ax.axvspan(0.67, 1.5, color="0.9", label="target band 0.67-1.5")
    ax.plot([r[1] for r in rows], y, "o", mfc="none", color="C3", label="before")
    ax.plot([r[2] for r in rows], y, "o", color="C0", label="after")
    for i, (_, b, a) in enumerate(rows):
        ax.annotate("", (a, i), (b, i), arrowprops={"arrowstyle": "->", "color": "0.5"})
    ax.set_xscale("log")
    ax.set_yticks(y, [r[0] for r in rows])
    ax.invert_yaxis()
    ax.set_xlabel("cov scale (1: honest; above: too confident)")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def _qq_plot(d: np.ndarray, nu: float, scale: float, out: str, sets: int) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = np.sort(d)
    p = (np.arange(len(d)) + 0.5) / len(d)
    fig, ax = plt.subplots(figsize=(5.5, 5))
    ax.plot(np.sqrt(stats.chi2.ppf(p, 3)), d, ".", ms=3, label="against chi(3) (Gaussian)")
    ax.plot(np.sqrt(3 * scale * stats.f.ppf(p, 3, nu)), d, ".", ms=3,
            label=f"against the fitted t (nu {nu:g}, scale {scale:.2f})")
    top = float(d.max()) * 1.05
    ax.plot([0, top], [0, top], "k-", lw=0.8)
    ax.axhline(3, color="grey", lw=0.6, ls="--")
    ax.set_xlim(0, top)
    ax.set_ylim(0, top)
    ax.set_xlabel("expected Mahalanobis length (quantile)")
    ax.set_ylabel("answers' Mahalanobis length (sorted)")
    ax.set_title(f"{len(d)} answers of the default method, {sets} sets")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def _pose(seven: list[float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = seven[:3]
    out[:3, :3] = Rotation.from_quat(seven[3:]).as_matrix()
    return out


def landmarks(dataset: str, out: str | None) -> None:
    from reloc_service.algorithms.pose import map_consistency as mc
    from reloc_service.algorithms.pose.pnp import refined_estimate
    from reloc_service.algorithms.pose.pnp_conf import PnPConf
    from reloc_service.algorithms.relocalizers import base as relocalizer_base
    from reloc_service.algorithms.relocalizers import multi
    from reloc_service.tools.eval import evaluate, inprocess

    truth: dict[int, np.ndarray] = {}
    origin: dict[int, np.ndarray] = {}   # centre of the keyframe a landmark's truth is from
    held: list[dict[str, Any]] = []
    seen: dict[str, Any] = {}
    conf = PnPConf()

    def on_map(backend: Any, data: Any) -> np.ndarray:
        state = seen["state"] = backend.engine.map.snapshot()
        for i, (point, centre) in _true_points(state, data).items():
            truth[i], origin[i] = point, centre
        for kind in sorted({k for kf in state.keyframes.values() for k in kf.features}):
            held.extend(_held_out(state, kind, conf, mc, refined_estimate))
        return np.zeros(0)

    answers: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def on_result(estimate: Any, c: Any, **kwargs: Any) -> Any:
        result = relocalizer_base.result_from_estimate(estimate, c, **kwargs)
        if estimate.inlier_landmark_ids is not None and estimate.inlier_px is not None:
            answers.append((estimate.world_from_cam.copy(), np.asarray(estimate.inlier_px),
                            np.asarray(estimate.inlier_landmark_ids)))
        return result

    inprocess.InProcessBackend.landmark_errors_m = on_map  # type: ignore[method-assign]
    multi.result_from_estimate = on_result
    result = evaluate.evaluate(dataset, "sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p",
                               progress=False)
    state = seen["state"]
    camera = next(iter(state.keyframes.values())).camera
    rows = []
    for q in result.methods[0].queries:
        if not q.returned or q.t_err_mahalanobis is None:
            continue
        world_from_cam, px, ids = min(answers, key=lambda a: float(np.linalg.norm(
            a[0][:3, 3] - np.asarray(q.est_world_from_cam[:3]))))
        known = np.array([int(i) in truth for i in ids])
        if known.sum() < 8:
            continue
        gt = _pose(q.gt_world_from_cam)
        errors = []
        for points in (state.landmark_points(ids[known]),
                       np.array([truth[int(i)] for i in ids[known]])):
            got = refined_estimate(world_from_cam, px[known].astype(np.float64), points, camera,
                                   conf)
            errors.append(math.nan if got is None else
                          float(np.linalg.norm(got[0].world_from_cam[:3, 3] - gt[:3, 3])))
        rows.append({"image": q.image_path, "step": q.method_used, "mahalanobis":
                     q.t_err_mahalanobis, "t_err_m": q.t_err_m, "inliers": int(known.sum()),
                     "resolved_on_map_m": errors[0], "resolved_on_truth_m": errors[1]})
    _print_landmarks(rows, held)
    _print_depth_errors(state, truth, origin)
    if out:
        Path(out).write_text(json.dumps({"answers": rows, "held_out_keyframes": held}, indent=1))


def _true_points(state: Any, data: Any) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Landmark id -> its ground-truth point (its first observation's pixel lifted with that
    keyframe's true depth) and that keyframe's centre, for the landmarks whose first
    observation has a valid true depth."""
    from reloc_service.core.mapping import first_observations, lift_pixels, sample_depth

    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for kind in sorted({k for kf in state.keyframes.values() for k in kf.features}):
        for kf_id, (ids, px) in first_observations(state, kind).items():
            depth = data.load_truth_depth(data.map_entries[kf_id])
            if depth is None or not len(ids):
                continue
            kf = state.keyframes[kf_id]
            z, valid = sample_depth(depth, px, max_jump=0.03)
            for i, p in zip(ids[valid], lift_pixels(kf.camera, kf.world_from_cam, px[valid],
                                                    z[valid]), strict=True):
                out.setdefault(int(i), (p, kf.position_world))
    return out


def _held_out(state: Any, kind: str, conf: Any, mc: Any, refined_estimate: Any
              ) -> list[dict[str, Any]]:
    """Each keyframe relocalized on its ``kind`` landmarks re-triangulated without it: its
    position error against its known pose and that error's Mahalanobis length under the PnP
    model covariance."""
    from reloc_service.algorithms.pose import held_out

    columns = mc._Columns(state)
    out = []
    for kf_id in state.keyframe_ids():
        kf = state.keyframes[kf_id]
        feats = kf.features.get(kind)
        if feats is None:
            continue
        observed, rows = held_out.held_out_candidates(columns.get(), feats.landmark_ids)
        points, held = held_out.held_out_points(state, columns.get(), rows, kf_id, kind)
        if held.sum() < mc.MIN_HELD_OUT:
            continue
        got = refined_estimate(kf.world_from_cam, feats.keypoints_px[observed[held]]
                               .astype(np.float64), points[held], kf.camera, conf)
        if got is None:
            continue
        est = got[0]
        err = est.world_from_cam[:3, :3].T @ (kf.world_from_cam[:3, 3] - est.world_from_cam[:3, 3])
        length = math.sqrt(float(err @ np.linalg.solve(est.covariance[:3, :3], err)))
        out.append({"keyframe": int(kf_id), "kind": kind, "inliers": int(est.inliers or 0),
                    "t_err_m": float(np.linalg.norm(err)), "mahalanobis": length})
    return out


def _print_depth_errors(state: Any, truth: dict[int, np.ndarray],
                        origin: dict[int, np.ndarray]) -> None:
    """The map's landmark errors along the ray of the keyframe their truth is from: signed
    (negative: nearer than the truth), and in units of their stated depth sigmas (the median
    of an honest |error| / sigma is 0.67)."""
    ids = np.array(sorted(truth), np.int64)
    if not len(ids):
        return
    true = np.array([truth[int(i)] for i in ids])
    ray = true - np.array([origin[int(i)] for i in ids])
    ranges = np.linalg.norm(ray, axis=1)
    along = np.einsum("ij,ij->i", state.landmark_points(ids) - true, ray / ranges[:, None])
    sigmas = state.landmark_sigmas(ids)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.abs(along) / sigmas
    print(f"landmarks ({len(ids)}): error along the ray median |{100 * np.median(np.abs(along)):.1f}| cm, "
          f"signed mean {100 * np.mean(along):.1f} cm at a median range of {np.median(ranges):.2f} m; "
          f"|error| / stated sigma median {np.median(z[np.isfinite(z)]):.2f} (0.67 honest)")


def _print_landmarks(rows: list[dict[str, Any]], held: list[dict[str, Any]]) -> None:
    rows = sorted(rows, key=lambda r: -r["mahalanobis"])
    tail = [r for r in rows if r["mahalanobis"] > 3]
    print("| answer | step | Mahalanobis | error cm | inliers | again on the map's points cm "
          "| again on the true points cm |")
    print("|---|---|---|---|---|---|---|")
    for r in tail:
        print(f"| {Path(r['image']).name} | {r['step']} | {r['mahalanobis']:.2f} | "
              f"{100 * r['t_err_m']:.2f} | {r['inliers']} | {100 * r['resolved_on_map_m']:.2f} | "
              f"{100 * r['resolved_on_truth_m']:.2f} |")
    for name, part in (("beyond 3 sigma", tail), ("all answers", rows)):
        on_map = np.array([r["resolved_on_map_m"] for r in part])
        on_truth = np.array([r["resolved_on_truth_m"] for r in part])
        if len(part):
            print(f"{name} ({len(part)}): median error again on the map's points "
                  f"{100 * np.nanmedian(on_map):.2f} cm, on the true points "
                  f"{100 * np.nanmedian(on_truth):.2f} cm")
    for kind in sorted({h["kind"] for h in held}):
        d = np.array([h["mahalanobis"] for h in held if h["kind"] == kind])
        print(f"held-out keyframes, {kind}: {len(d)}, cov scale {np.median(d) / CHI3_MEDIAN:.2f}, "
              f"second-moment scale {math.sqrt(np.mean(d**2) / 3):.2f}, beyond 3 sigma "
              f"{int((d > 3).sum())} ({100 * np.mean(d > 3):.1f} %)")


def provenance(dataset: str) -> None:
    from reloc_service.algorithms.relocalizers import base as relocalizer_base
    from reloc_service.algorithms.relocalizers import multi
    from reloc_service.core import map as core_map
    from reloc_service.tools.eval import evaluate, inprocess

    created: dict[int, tuple[np.ndarray, float, int]] = {}
    moves: dict[int, int] = {}
    add, move = core_map.KeyframeMap.add_landmarks, core_map.KeyframeMap.move_landmarks

    def on_add(self: Any, kind: str, points: Any, observations: Any, **kwargs: Any) -> Any:
        ids = add(self, kind, points, observations, **kwargs)
        state = self.snapshot()
        for i in ids:
            lm = state.landmarks[i]
            created[i] = (lm.point_world.copy(), float(state.landmark_sigmas([i])[0]),
                          len(lm.observations))
        return ids

    def on_move(self: Any, landmark_ids: Any, points: Any) -> Any:
        for i in np.asarray(landmark_ids).ravel().tolist():
            moves[i] = moves.get(i, 0) + 1
        return move(self, landmark_ids, points)

    truth: dict[int, np.ndarray] = {}
    final: dict[int, tuple[np.ndarray, int]] = {}

    def on_map(backend: Any, data: Any) -> np.ndarray:
        state = backend.engine.map.snapshot()
        truth.update({i: point for i, (point, _) in _true_points(state, data).items()})
        for i in truth:
            lm = state.landmarks[i]
            final[i] = (lm.point_world.copy(), len(lm.observations))
        return np.zeros(0)

    inlier_ids: list[np.ndarray] = []

    def on_result(estimate: Any, c: Any, **kwargs: Any) -> Any:
        result = relocalizer_base.result_from_estimate(estimate, c, **kwargs)
        if result.ok and estimate.inlier_landmark_ids is not None:
            inlier_ids.append(np.asarray(estimate.inlier_landmark_ids))
        return result

    core_map.KeyframeMap.add_landmarks = on_add  # type: ignore[method-assign]
    core_map.KeyframeMap.move_landmarks = on_move  # type: ignore[method-assign]
    inprocess.InProcessBackend.landmark_errors_m = on_map  # type: ignore[method-assign]
    multi.result_from_estimate = on_result
    evaluate.evaluate(dataset, "sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p", progress=False)
    ids = np.array(sorted(i for i in final if i in created), np.int64)
    true = np.array([truth[int(i)] for i in ids])
    at_birth = np.linalg.norm(np.array([created[int(i)][0] for i in ids]) - true, axis=1)
    at_end = np.linalg.norm(np.array([final[int(i)][0] for i in ids]) - true, axis=1)
    sigma = np.array([created[int(i)][1] for i in ids])
    born_obs = np.array([created[int(i)][2] for i in ids])
    end_obs = np.array([final[int(i)][1] for i in ids])
    moved = np.array([moves.get(int(i), 0) > 0 for i in ids])
    print(f"{len(ids)} landmarks with a ground truth, {int(moved.sum())} moved by track "
          "refinement")
    print("| error at the end | landmarks | error when created (median) | moved | stated sigma "
          "when created (median) | observations when created / at the end (median) |")
    print("|---|---|---|---|---|---|")
    for lo, hi in ((0.0, 0.1), (0.1, 0.3), (0.3, 1.0), (1.0, math.inf)):
        sel = (at_end >= lo) & (at_end < hi)
        if sel.any():
            print(f"| {100 * lo:.0f}-{100 * hi:.0f} cm | {int(sel.sum())} | "
                  f"{100 * np.median(at_birth[sel]):.0f} cm | {100 * np.mean(moved[sel]):.0f} % | "
                  f"{100 * np.median(sigma[sel]):.1f} cm | {np.median(born_obs[sel]):.0f} / "
                  f"{np.median(end_obs[sel]):.0f} |")
    far = {int(i) for i in ids[at_end > 0.3]}
    known = set(ids.tolist())
    for n, answer in enumerate(inlier_ids):
        scored = [int(i) for i in answer if int(i) in known]
        print(f"verified pose {n}: {len(answer)} inliers, {len(scored)} with a ground truth, "
              f"{sum(i in far for i in scored)} of them more than 30 cm off")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    t = sub.add_parser("table", help="tails of reloc eval JSON files")
    t.add_argument("evals", nargs="+")
    t.add_argument("--plot")
    sc = sub.add_parser("scales", help="cov scales of two directories of reloc eval JSON")
    sc.add_argument("before")
    sc.add_argument("after")
    sc.add_argument("--plot")
    lm = sub.add_parser("landmarks", help="answers solved again on true landmark points")
    lm.add_argument("dataset")
    lm.add_argument("--out")
    pv = sub.add_parser("provenance", help="where a synthetic map's landmark errors were made")
    pv.add_argument("dataset")
    args = parser.parse_args()
    if args.command == "table":
        table(args.evals, args.plot)
    elif args.command == "scales":
        scales(args.before, args.after, args.plot)
    elif args.command == "provenance":
        provenance(args.dataset)
    else:
        landmarks(args.dataset, args.out)


if __name__ == "__main__":
    main()
