"""``reloc bench --only prior``: localization with a prior, measured. Every query of each
dataset is answered by the default method without a prior, with a good prior (its
ground-truth pose perturbed by a draw from the stated covariance: 5 cm and 2 deg, 1 sigma per
axis, as a VIO gives it) and with a wrong one (2 m or 30 deg off, the same small covariance
stated: a VIO that drifted or reset).

Per set: p50 latency (relocalize from the decoded grey image, as the accuracy section times
it) against the p50 of decode + ORB extraction (:mod:`.limit`) of the same queries, recall
within 5 cm / 5 deg, wrong poses (beyond 0.5 m / 15 deg, ``reloc eval``'s definition), the
cov scale of the answers (``reloc eval``'s: 1 when the stated covariance fits the errors),
the share answered by the tracking step; for wrong priors, the answers within that threshold
of the wrong prior.
"""

from __future__ import annotations

import functools
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...algorithms.relocalizers.base import Prior
from ...algorithms.relocalizers.tracking import TRACK
from ...core.frame import Frame
from ...core.geometry import pose_covariance_from_sigmas, pose_error, se3_exp
from ..eval.metrics import WRONG_THRESHOLD, covariance_scale, translation_mahalanobis
from ..eval.results import json_safe
from .limit import LIMIT_ORB_FEATURES, limit_summary, measure_limit

Array = npt.NDArray[np.float64]

SCHEMA = "reloc-bench-prior/1"
#: The good prior's 1-sigma error per axis (metres, degrees): a VIO's drift between fixes.
SIGMA_M, SIGMA_DEG = 0.05, 2.0
#: Recall threshold (metres, degrees).
RECALL = (0.05, 5.0)
#: The runs of every query, in table order.
RUNS = ("no prior", "prior 5cm/2deg", "prior 2 m off", "prior 30 deg off")
#: Synthetic presets scored when no dataset is named (with the real sets): a room and a
#: stereo rig's revisits.
PRESETS: tuple[str, ...] = ("room", "stereo")
#: The real sets' ground-truth accuracy (metres, degrees, 1 sigma per axis; the sets'
#: README), with which their keyframes are put, as ``reloc eval --keyframe-sigma`` puts them:
#: a prior-anchored tracker pools landmarks of several keyframes and weighs them by the
#: keyframes' pose errors. A set not named here (a rendered one) has exact poses.
KEYFRAME_SIGMAS: dict[str, tuple[float, float]] = {
    "tum_fr1_rpy": (0.01, 0.3), "7scenes_redkitchen": (0.015, 0.45),
    "strecha_fountain_p11": (0.002, 0.01), "strecha_herzjesu_p25": (0.002, 0.01)}


@dataclass(frozen=True)
class PriorConf:
    """What the section runs on: dataset folders, rendered ``presets`` (into ``cache``), the
    real sets found beside the project (``real_sets``), good priors drawn per query, the seed
    of the draws."""

    datasets: tuple[Path, ...] = ()
    presets: tuple[str, ...] = PRESETS
    real_sets: bool = True
    repeats: int = 3
    seed: int = 0
    scale: float = 1.0
    cache: Path | None = None
    method: str | None = None  # None: the service config's default method


def good_prior(gt_world_from_cam: Array, rng: np.random.Generator) -> Array:
    """``gt_world_from_cam`` moved by a draw of the stated covariance (in the camera frame)."""
    xi = np.concatenate([rng.normal(0, SIGMA_M, 3), rng.normal(0, np.deg2rad(SIGMA_DEG), 3)])
    return gt_world_from_cam @ se3_exp(xi)


def shifted_prior(gt_world_from_cam: Array, rng: np.random.Generator) -> Array:
    """``gt_world_from_cam`` moved 2 m in a random direction."""
    direction = rng.normal(size=3)
    out = gt_world_from_cam.copy()
    out[:3, 3] += 2.0 * direction / np.linalg.norm(direction)
    return out


def turned_prior(gt_world_from_cam: Array, rng: np.random.Generator) -> Array:
    """``gt_world_from_cam`` turned 30 deg about a random axis through its centre."""
    axis = rng.normal(size=3)
    return gt_world_from_cam @ se3_exp(np.concatenate(
        [np.zeros(3), np.deg2rad(30.0) * axis / np.linalg.norm(axis)]))


def summarize(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One run's row: p50, answers, recall, wrong poses, answers near the wrong prior, cov
    scale (NaN without an answer), answers whose position error lies beyond 3 sigma of
    their stated covariance, answers by the tracking step."""
    lat = [r["ms"] for r in records]
    return {"n": len(records), "p50_ms": float(np.median(lat)) if lat else None,
            "answered": sum(bool(r["ok"]) for r in records),
            "recall_5cm_5deg": float(np.mean([r["ok"] and r["t"] <= RECALL[0]
                                              and r["r"] <= RECALL[1] for r in records]))
            if records else None,
            "wrong": sum(r["ok"] and (r["t"] > WRONG_THRESHOLD[0] or r["r"] > WRONG_THRESHOLD[1])
                         for r in records),
            "near_wrong_prior": sum(r.get("near_prior", False) for r in records),
            "cov_scale": covariance_scale([r.get("mahalanobis", np.nan) for r in records],
                                          [r["ok"] for r in records]) if records else None,
            # a 3-D Gaussian puts 2.9 % of honest answers there (compare_eval.py's count)
            "beyond_3_sigma": sum(bool(r["ok"]) and r.get("mahalanobis", 0.0) > 3.0
                                  for r in records),
            "by_track": sum(r["method"] == TRACK for r in records)}


def _ask(engine: Any, method: str, image: npt.NDArray[np.uint8], camera: Any, gt: Array,
         prior_pose: Array | None, covariance: Array, wrong_prior: bool) -> dict[str, Any]:
    """One query answered with ``prior_pose`` (or none), timed and scored."""
    prior = None if prior_pose is None else Prior(prior_pose, covariance=covariance)
    start = time.perf_counter()
    result = engine.relocalize(Frame(image, camera), method=method, prior=prior)
    rec: dict[str, Any] = {"ok": result.ok, "ms": (time.perf_counter() - start) * 1e3,
                           "method": result.method, "t": np.inf, "r": np.inf}
    if result.ok:
        t, r = pose_error(result.world_from_cam, gt)
        rec["t"], rec["r"] = t, float(np.degrees(r))
        if result.covariance is not None:
            rec["mahalanobis"] = translation_mahalanobis(result.world_from_cam, gt,
                                                         result.covariance)
        if prior_pose is not None and wrong_prior:
            # Within the wrong-pose threshold of the wrong prior (2 m or 30 deg from the
            # truth: the two neighbourhoods do not overlap).
            t, r = pose_error(result.world_from_cam, prior_pose)
            rec["near_prior"] = bool(t <= WRONG_THRESHOLD[0]
                                     and np.degrees(r) <= WRONG_THRESHOLD[1])
    return rec


def bench_set(root: Path, method: str, *, repeats: int, seed: int,
              keyframe_sigma: tuple[float, float] = (0.0, 0.0)) -> dict[str, Any]:
    """Build ``root``'s map as ``reloc eval --keyframe-sigma`` does, then every query without
    a prior, with ``repeats`` good priors and with the two wrong ones, the limit timed
    alongside."""
    from ..data.dataset import read_dataset
    from ..eval import evaluate as ev
    from .accuracy import eval_default_landmarks

    dataset = read_dataset(root)
    source = eval_default_landmarks()
    ev._check_dataset(dataset, source)
    options = ev.options_stating_dataset_calibration(None, dataset) or {}
    backend = ev.InProcessBackend([method], {k: dict(v) for k, v in options.items()}, source)
    covariance = pose_covariance_from_sigmas(SIGMA_M, np.deg2rad(SIGMA_DEG))
    rng = np.random.default_rng(seed)
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in RUNS}
    limit: dict[str, list[float]] = {}
    try:
        ev._build_map(backend, dataset, source, False, ev.ground_truth_covariance(keyframe_sigma))
        backend.train(progress=False)
        ask = functools.partial(_ask, backend.engine, method, covariance=covariance)
        for entry in dataset.query_entries:
            measure_limit(functools.partial(dataset.load_image, entry), limit,
                          {"orb": LIMIT_ORB_FEATURES})
            image, camera = dataset.load_image(entry), dataset.camera(entry)
            gt = np.array(entry.world_from_cam)
            runs["no prior"].append(ask(image, camera, gt, None, wrong_prior=False))
            for _ in range(repeats):
                runs["prior 5cm/2deg"].append(ask(image, camera, gt, good_prior(gt, rng),
                                                  wrong_prior=False))
            runs["prior 2 m off"].append(ask(image, camera, gt, shifted_prior(gt, rng),
                                             wrong_prior=True))
            runs["prior 30 deg off"].append(ask(image, camera, gt, turned_prior(gt, rng),
                                                wrong_prior=True))
    finally:
        backend.close()
    limits = limit_summary(limit) if limit else {}
    bound = limits.get("orb_limit_p50_ms")
    rows = {name: summarize(recs) for name, recs in runs.items()}
    for row in rows.values():
        row["over_limit"] = row["p50_ms"] / bound if bound and row["p50_ms"] else None
    return {"root": str(Path(root).resolve()), "queries": len(dataset.query_entries),
            "keyframe_sigma": list(keyframe_sigma),
            "limit": {**limits, "orb_features": LIMIT_ORB_FEATURES}, "runs": rows}


def bench_prior(conf: PriorConf, workdir: Path, say: Callable[[str], None] = print
                ) -> dict[str, Any]:
    """Every dataset of ``conf`` (presets rendered first); a failing one is recorded and
    the others still run."""
    from .accuracy import default_real_root, real_sets, service_default_method
    from .workspace import render_cached

    method = conf.method or service_default_method()
    roots: list[tuple[str, Any]] = [("synth", p) for p in conf.presets]
    roots += [("dir", Path(d)) for d in conf.datasets]
    if conf.real_sets:
        roots += [("dir", d) for d in real_sets(default_real_root())[0]]
    sets: dict[str, Any] = {}
    for kind, what in roots:
        name = what if kind == "synth" else Path(what).name
        say(f"prior: dataset {name}")
        try:
            root = what if kind == "dir" else render_cached(
                what, conf.cache or workdir / "cache", seed=0, scale=conf.scale, workers=1,
                show=False)[0]
            sets[name] = bench_set(root, method, repeats=conf.repeats, seed=conf.seed,
                                   keyframe_sigma=KEYFRAME_SIGMAS.get(name, (0.0, 0.0)))
        except Exception as exc:  # the other sets' figures still count
            traceback.print_exc()
            sets[name] = {"error": f"{type(exc).__name__}: {exc}"}
        # Each set's rows as soon as it is done: a long run shows its figures as it goes.
        say("\n".join(table_lines({"sets": {name: sets[name]}})[2:]))
    return {"schema": SCHEMA, "method": method, "sigma_m": SIGMA_M, "sigma_deg": SIGMA_DEG,
            "repeats": conf.repeats, "runs": list(RUNS), "sets": sets,
            "failed_sets": [k for k, v in sets.items() if "error" in v]}


def run_into(result: dict[str, Any], conf: PriorConf, workdir: Path | None,
             say: Callable[[str], None]) -> None:
    """Run the section into ``result["prior"]`` (an ``{"error": ...}`` if it failed)."""
    import contextlib
    import tempfile

    start = time.perf_counter()
    try:
        with contextlib.ExitStack() as stack:
            tmp = workdir or Path(stack.enter_context(tempfile.TemporaryDirectory(
                prefix="reloc-bench-prior-")))
            result["prior"] = json_safe(bench_prior(conf, tmp, say))
    except Exception as exc:  # the error is the section's result, as for the others
        traceback.print_exc()
        result["prior"] = {"error": f"{type(exc).__name__}: {exc}"}
        return
    result.setdefault("section_seconds", {})["prior"] = time.perf_counter() - start


def _num(value: Any, fmt: str) -> str:
    return "-" if value is None or value != value else format(value, fmt)  # None or NaN


def table_lines(section: Mapping[str, Any]) -> list[str]:
    """One row per set and run: p50, the limit, their ratio, recall, wrong, cov scale, near
    the wrong prior, by the tracking step."""
    lines = ["| set | run | p50 ms | decode + ORB p50 ms | p50 / limit | recall 5cm/5deg | "
             "wrong | cov scale | near wrong prior | by track |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in section["sets"].items():
        if "error" in s:
            lines.append(f"| {name} | failed | - | - | - | - | - | - | - | - |")
            continue
        bound = s["limit"].get("orb_limit_p50_ms")
        for run, row in s["runs"].items():
            lines.append(f"| {name} | {run} | {_num(row['p50_ms'], '.1f')} | "
                         f"{_num(bound, '.1f')} | {_num(row['over_limit'], '.2f')} | "
                         f"{_num(row['recall_5cm_5deg'], '.0%')} | {row['wrong']} | "
                         f"{_num(row.get('cov_scale'), '.2f')} | "
                         f"{row['near_wrong_prior']} | {row['by_track']}/{row['n']} |")
    return lines


def markdown_lines(section: Mapping[str, Any]) -> list[str]:
    """The section of ``docs/performance.md``."""
    return [HEADING, "",
            f"Method `{section['method']}` through `Engine.relocalize`, timed from the decoded "
            f"grey image; limit: p50 of reading and decoding each query image and extracting "
            f"{LIMIT_ORB_FEATURES} ORB features, timed on the same queries in the same run. "
            f"Priors: each query's ground truth perturbed by a draw from the stated covariance "
            f"({section['sigma_m'] * 100:.0f} cm, {section['sigma_deg']:.0f} deg, 1 sigma per "
            f"axis; {section['repeats']} draws per query), or moved 2 m / turned 30 deg in a "
            f"random direction with the same small covariance stated. Recall within "
            f"{RECALL[0] * 100:.0f} cm / {RECALL[1]:.0f} deg; wrong: returned beyond "
            f"{WRONG_THRESHOLD[0]} m / {WRONG_THRESHOLD[1]:.0f} deg; cov scale: the median "
            f"Mahalanobis length of the answers' position errors under their stated "
            f"covariance over its value for honest Gaussian errors (1: honest, 2: twice too "
            f"confident; `reloc eval`'s); near wrong prior: returned "
            f"within that threshold of the wrong prior; by track: answers given by the "
            f"tracking step (`method == \"{TRACK}\"`), the rest by the chain.", "",
            *table_lines(section), ""]


#: The heading of the section in ``docs/performance.md``.
HEADING = "## Localization with a prior"


def splice_markdown(existing: str, section: Mapping[str, Any], generated_by: str) -> str:
    """``existing`` (a ``docs/performance.md`` written by a full run) with its prior section
    replaced by this run's (or appended where it has none): from :data:`HEADING` to the
    next ``## `` heading. The section names the run it comes from, ``generated_by``, since
    the rest of the file comes from another."""
    lines = existing.rstrip("\n").split("\n")
    new = markdown_lines(section)
    new[1:1] = ["", f"Generated by `{generated_by}`; the other sections come from the run "
                    f"named at the top."]
    if HEADING not in lines:
        return "\n".join([*lines, "", *new]).rstrip("\n") + "\n"
    start = lines.index(HEADING)
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")),
               len(lines))
    return "\n".join([*lines[:start], *new, *lines[end:]]).rstrip("\n") + "\n"
