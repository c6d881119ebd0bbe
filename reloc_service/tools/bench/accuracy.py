"""``reloc bench --only accuracy``: recall of reloc's methods side by side with the plain
OpenCV pipeline (:mod:`.peers`), on every evaluation set, in one table.

For each dataset the map is built once, in-process, exactly as ``reloc eval`` builds it with
its default options: eval's own checks, :class:`~reloc_service.tools.eval.evaluate.InProcessBackend`
and map-building step (every ``map.txt`` keyframe added with its row as id, landmarks from
``evaluate``'s default landmark source), then every method trained. The plain OpenCV peer gets the
landmark descriptors of that same map (:meth:`.peers.PlainMap.from_state`). Then every query
of ``queries.txt`` is answered by every method and by the peer in turn (query by query, so
that machine load hits every column alike), each answer timed as ``reloc eval`` times it
(decoded grey image in, pose out) and scored by ``reloc eval``'s own code
(:func:`~reloc_service.tools.eval.evaluate.record_from_result` and
:func:`~reloc_service.tools.eval.evaluate.summarize`, i.e. :mod:`reloc_service.tools.eval.metrics`):
recall at 5 cm / 5 deg and 25 cm / 10 deg, wrong rate (returned but beyond 50 cm or
15 deg), p50 latency.

Datasets: ``--dataset DIR`` (repeatable) and ``--preset NAME`` (repeatable, rendered into the
bench workdir); with neither, the presets of :data:`QUICK_PRESETS` / :data:`FULL_PRESETS` plus
every set under ``../shared/data/real/*/`` next to the repository (skipped with a note when
that folder is absent).
"""

from __future__ import annotations

import dataclasses
import functools
import time
import traceback
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...algorithms.relocalizers.base import RelocResult, RelocStatus
from ...core.methods import MethodSpec, parse_method
from ...core.numeric import limit_blas_threads
from ...core.progress import progress
from ..eval.results import json_safe
from .limit import LIMIT_ORB_FEATURES, limit_summary, measure_limit, over_limit
from .workspace import say

#: reloc's methods in every table, besides the service's default method.
RELOC_METHODS: tuple[str, ...] = ("sbi+p3p", "bow+p3p", "ferns")
#: The plain OpenCV peer as a user would write it, and as a careful user would (one
#: descriptor per landmark): column key -> (label, ``PlainMap.from_state(dedupe=...)``).
PEERS: dict[str, tuple[str, bool]] = {
    "plain_opencv": ("plain OpenCV", False),
    "plain_opencv_dedup": ("plain OpenCV, dedup", True)}
#: Synthetic presets rendered when no dataset or preset is named.
QUICK_PRESETS: tuple[str, ...] = ("desk",)
FULL_PRESETS: tuple[str, ...] = ("desk", "room", "room-hard")
#: Recall thresholds in the table (keys of :func:`metrics.threshold_key`).
TABLE_RECALLS: tuple[str, ...] = ("5cm_5deg", "25cm_10deg")
SCHEMA = "reloc-bench-accuracy/1"
#: How a column's error starts when the column does not apply (the peer on a FOV camera); any
#: other column error is a failure of the run.
NOT_APPLICABLE = "not applicable"
#: Keys of every column's summary (the JSON schema of one cell).
SUMMARY_KEYS: tuple[str, ...] = (
    "queries", "returned", "recall", "wrong_rate", "off_rate", "covariance_scale",
    "covariance_rms_scale", "beyond_3_sigma", "returned_rate", "not_relocalized_rate",
    "median_t_err_m",
    "median_r_err_deg", "p50_ms", "p90_ms", "p99_ms")


def repo_root() -> Path:
    """The repository holding this package (``reloc_service/tools/bench/accuracy.py``)."""
    return Path(__file__).resolve().parents[3]


def default_real_root() -> Path:
    """``../shared/data/real`` relative to the repository root."""
    return (repo_root() / ".." / "shared" / "data" / "real").resolve()


def service_default_method() -> str:
    """``service.default_method`` of the service's default configuration (what ``reloc
    serve --print-config`` prints without ``--config``)."""
    from ...service.config import load_config

    return load_config(None).service.default_method


@dataclass(frozen=True)
class AccuracyConf:
    """What the accuracy section runs on. ``real_root`` None: no real sets; ``scale``
    shrinks rendered presets (tests only: the bench renders at full size)."""

    presets: tuple[str, ...] = FULL_PRESETS
    datasets: tuple[Path, ...] = ()
    real_root: Path | None = None
    seed: int = 0
    scale: float = 1.0
    methods: tuple[str, ...] = RELOC_METHODS
    default_method: str | None = None  # None: the service config's
    render_workers: int = 2
    #: Methods scored on the synthetic presets only (ferns: training it on every set takes
    #: longer than the whole benchmark's budget); their cells elsewhere say so.
    synth_only: tuple[str, ...] = ()
    #: Peer columns (keys of :data:`PEERS`).
    peers: tuple[str, ...] = tuple(PEERS)
    #: Rendered presets are kept here and reused (:func:`.workspace.render_cached`); None:
    #: ``<workdir>/cache``.
    cache: Path | None = None
    #: Why the real sets are not scored (e.g. a quick run), or None.
    real_skipped: str | None = None
    #: Plugin options of the eval backend (as ``reloc eval --options``).
    options: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)

    def columns(self) -> tuple[list[str], str]:
        """reloc's methods in column order (the default method added once) and the default."""
        default = self.default_method or service_default_method()
        methods = list(dict.fromkeys([*self.methods, default]))
        return methods, default


def conf_from_args(*, quick: bool, presets: Sequence[str] | None,
                   datasets: Sequence[Path] | None, seed: int = 0,
                   real_root: Path | None = None) -> AccuracyConf:
    """``--preset``/``--dataset`` as given; with neither, the default presets (desk only
    with ``--quick``) plus the real sets of ``real_root`` (default: next to the repository)."""
    if presets or datasets:
        return AccuracyConf(presets=tuple(presets or ()), datasets=tuple(datasets or ()),
                            real_root=None, seed=seed)
    return AccuracyConf(presets=QUICK_PRESETS if quick else FULL_PRESETS,
                        real_root=real_root or default_real_root(), seed=seed)


def bench_conf(*, quick: bool, real_root: Path | None, seed: int = 0, scale: float = 1.0,
               cache: Path | None = None,
               options: Mapping[str, Mapping[str, Any]] | None = None) -> AccuracyConf:
    """The accuracy section of a whole ``reloc bench`` run (no ``--only``): the default
    method and ``sbi+p3p`` (SIFT) with the plain OpenCV peer on the presets and every real
    set, ferns on the presets only; ``--quick`` scores desk alone and skips the real sets."""
    conf = AccuracyConf(presets=QUICK_PRESETS if quick else FULL_PRESETS,
                        real_root=None if quick else (real_root or default_real_root()),
                        seed=seed, scale=scale, methods=("sbi+p3p", "ferns"),
                        synth_only=("ferns",), peers=("plain_opencv",), cache=cache,
                        options=dict(options or {}),
                        real_skipped="the quick run skips the real sets" if quick else None)
    return conf


def check_conf(conf: AccuracyConf) -> str | None:
    """A usage problem of ``conf`` (unknown preset, dataset folder without queries), or None."""
    from ..synth.presets import PRESETS

    unknown = [p for p in conf.presets if p not in PRESETS]
    if unknown:
        return f"unknown preset(s) {unknown}; expected some of {sorted(PRESETS)}"
    for d in conf.datasets:
        if not (Path(d) / "queries.txt").is_file() or not (Path(d) / "map.txt").is_file():
            return f"--dataset {d}: not a reloc dataset with map.txt and queries.txt"
    return None


def real_sets(root: Path | None) -> tuple[list[Path], list[str]]:
    """The dataset folders ``root/*/`` (those with map.txt and queries.txt) and notes on what
    was skipped."""
    if root is None:
        return [], []
    if not root.is_dir():
        return [], [f"real sets: {root} is absent; skipped"]
    found, notes = [], []
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        if (d / "map.txt").is_file() and (d / "queries.txt").is_file():
            found.append(d)
        else:
            notes.append(f"real sets: {d.name} has no map.txt and queries.txt; skipped")
    if not found:
        notes.append(f"real sets: no dataset under {root}")
    return found, notes


# -- the section -------------------------------------------------------------------------------

def bench_accuracy(conf: AccuracyConf, workdir: Path, *, show_progress: bool = True
                   ) -> dict[str, Any]:
    """Render the presets into ``workdir``, then score every method and peer on every
    dataset (a failing dataset is recorded, the others still run)."""
    cv2.setNumThreads(1)  # as the rest of the bench (one core per service worker)
    limit_blas_threads(1)
    methods, default = conf.columns()
    reals, notes = real_sets(conf.real_root)
    if conf.real_skipped:
        notes.append(f"real sets: skipped ({conf.real_skipped})")
    notes += [f"`{m}`: scored on the synthetic presets only (training it on every set "
              "takes longer than the benchmark's budget)" for m in conf.synth_only
              if m in methods]
    jobs: list[tuple[str, str, Any]] = (
        [("synth", p, p) for p in conf.presets]
        + [("dir", Path(d).name, Path(d)) for d in conf.datasets]
        + [("real", d.name, d) for d in reals])
    datasets: dict[str, Any] = {}
    for kind, name, what in jobs:
        key = _unique(name, datasets)
        say(f"accuracy: dataset {key} ({kind})")
        info: dict[str, Any] = {"kind": kind}
        try:
            if kind == "synth":
                info.update(preset=what, seed=conf.seed, scale=conf.scale)
                root, info["render_s"], info["render_cached"] = _render(
                    what, conf.cache or workdir / "cache", conf, show_progress)
                use = methods
            else:
                root = what
                use = [m for m in methods if m not in conf.synth_only]
            info.update(score_dataset(root, use, show_progress=show_progress,
                                      peers=conf.peers, options=conf.options))
        except Exception as exc:  # the other datasets' figures still count
            traceback.print_exc()
            info["error"] = f"{type(exc).__name__}: {exc}"
        datasets[key] = info
    return {"schema": SCHEMA, "methods": methods, "default_method": default,
            "peers": {k: label for k, (label, _) in PEERS.items() if k in conf.peers},
            "columns": [*methods, *conf.peers], "synth_only": list(conf.synth_only),
            "table_recalls": list(TABLE_RECALLS),
            "how": "map built once per dataset in-process as `reloc eval` does with its "
                   "default options; the plain OpenCV peer matches against the landmark "
                   "descriptors of that same map; each query answered by every column in "
                   "turn from the decoded grey image, timed and scored by `reloc eval`'s "
                   "code",
            "notes": notes, "datasets": datasets,
            "failed_datasets": [k for k, v in datasets.items() if "error" in v],
            "failed_columns": [f"{k}/{c}" for k, v in datasets.items()
                               for c, r in v.get("results", {}).items()
                               if "error" in r and not r["error"].startswith(NOT_APPLICABLE)]}


def _unique(name: str, taken: Mapping[str, Any]) -> str:
    key, n = name, 2
    while key in taken:
        key, n = f"{name}-{n}", n + 1
    return key


def _render(preset: str, cache: Path, conf: AccuracyConf, show: bool
            ) -> tuple[Path, float, bool]:
    from .workspace import render_cached

    return render_cached(preset, cache, seed=conf.seed, scale=conf.scale,
                         workers=conf.render_workers, show=show)


def score_dataset(root: Path, methods: Sequence[str], *, show_progress: bool = True,
                  peers: Sequence[str] = tuple(PEERS),
                  options: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """Build ``root``'s map as ``reloc eval`` does, train, then answer every query with every
    method of ``methods`` and the ``peers``; returns the dataset's record (see module doc)."""
    from ..data.dataset import read_dataset
    from ..eval import evaluate as ev

    dataset = read_dataset(root)
    source = eval_default_landmarks()
    # reloc eval's own steps (evaluate() without the method loop): the same checks, backend,
    # map building and training, so that the map is the one `reloc eval` scores on.
    ev._check_dataset(dataset, source)
    options = ev.options_stating_dataset_calibration(options, dataset)
    backend = ev.InProcessBackend(list(methods), {k: dict(v) for k, v in (options or {}).items()},
                                  source)
    try:
        # exact ground truth, as `reloc eval` without --keyframe-sigma takes it
        build_s = ev._build_map(backend, dataset, source, show_progress,
                                ev.ground_truth_covariance((0.0, 0.0)))
        start = time.perf_counter()
        backend.train(progress=show_progress)
        train_s = time.perf_counter() - start
        state = backend.engine.map.snapshot()
        peer_cols, peer_errors = _make_peers(state, {e.camera_id: dataset.camera(e)
                                                     for e in dataset.query_entries}, peers)
        records: dict[str, list[Any]] = {c: [] for c in [*methods, *peer_cols]}
        errors: dict[str, str] = dict(peer_errors)
        limit: dict[str, list[float]] = {}
        start = time.perf_counter()
        queries: Iterable[Any] = dataset.query_entries
        if show_progress:
            queries = progress(list(queries), desc=f"{Path(root).name}: queries")
        for entry in queries:
            measure_limit(functools.partial(dataset.load_image, entry), limit,
                          {"orb": LIMIT_ORB_FEATURES})
            _score_query(backend, dataset, entry, methods, peer_cols, records, errors)
        eval_s = time.perf_counter() - start
    finally:
        backend.close()
    results: dict[str, Any] = {}
    for column, recs in records.items():
        if column in errors:
            results[column] = {"error": errors[column]}
        else:
            results[column] = summary_dict(ev.summarize(recs))
            results[column]["p90_ms"] = (float(np.percentile([r.latency_ms for r in recs], 90))
                                         if recs else None)
            if column in PEERS:
                results[column]["map_descriptors"] = peer_cols[column]["descriptors"]
            elif len((spec := parse_method(column)).steps) > 1:
                results[column]["first_step"] = first_step_share(spec, recs)
    limits = limit_summary(limit) if limit else {}
    for column, ratio in over_limit(results, limits).items():
        results[column]["over_limit"] = ratio
    cams = sorted({dataset.camera(e).model for e in dataset.query_entries})
    return {"root": str(Path(root).resolve()), "landmark_source": source.value,
            "keyframes": len(state.keyframes),
            "landmarks": len(state.landmarks), "sift_landmarks": state.landmark_count("sift"),
            "queries": len(dataset.query_entries),
            "camera_models": cams, "build_s": build_s, "train_s": train_s, "eval_s": eval_s,
            "limit": {**limits, "orb_features": LIMIT_ORB_FEATURES}, "results": results}


def eval_default_landmarks() -> Any:
    """The :class:`~reloc_service.tools.eval.evaluate.LandmarkSource` ``reloc eval`` uses by default
    (the default of :func:`~reloc_service.tools.eval.evaluate.evaluate`'s ``landmarks``)."""
    import inspect

    from ..eval import evaluate as ev

    default = inspect.signature(ev.evaluate).parameters["landmarks"].default
    return ev.LandmarkSource(default)


def first_step_share(chain: MethodSpec, records: Sequence[Any]) -> dict[str, Any]:
    """Of a fallback chain's answers, how many its first step gave (a chain's result names
    the step that answered, :class:`~reloc_service.algorithms.relocalizers.chain.ChainRelocalizer`)."""
    step = str(chain.steps[0])
    returned = [r for r in records if r.returned]
    by_first = sum(r.method_used == step for r in returned)
    return {"step": step, "answered": by_first, "returned": len(returned),
            "share_of_returned": by_first / len(returned) if returned else None}


def _make_peers(state: Any, cameras: Mapping[str, Any], which: Sequence[str] = tuple(PEERS)
                ) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """Per peer: its map's descriptor count and one pipeline per query camera id, or an
    error when a camera is one the plain pipeline cannot take (fisheye, FOV)."""
    from .peers import PlainMap, PlainOpenCVPipeline

    peers: dict[str, dict[str, Any]] = {}
    errors: dict[str, str] = {}
    for key in which:
        plain = PlainMap.from_state(state, dedupe=PEERS[key][1])
        try:
            pipes = {ck: PlainOpenCVPipeline(plain, cam) for ck, cam in cameras.items()}
        except ValueError as exc:  # a camera model OpenCV's solvePnP does not take
            errors[key] = f"{NOT_APPLICABLE}: {exc}"
            pipes = {}
        peers[key] = {"descriptors": len(plain), "pipelines": pipes}
    return peers, errors


def _score_query(backend: Any, dataset: Any, entry: Any, methods: Sequence[str],
                 peers: Mapping[str, Mapping[str, Any]], records: dict[str, list[Any]],
                 errors: dict[str, str]) -> None:
    """One query by every column still running; a column that raises stops (error kept)."""
    from ..eval.evaluate import record_from_result

    image = dataset.load_image(entry)
    camera = dataset.camera(entry)
    gt = np.array(entry.world_from_cam)
    for method in methods:
        if method in errors:
            continue
        try:
            start = time.perf_counter()  # as reloc eval's _query: relocalize only
            result = backend.relocalize(image, camera, method=method, gt_world_from_cam=gt)
            latency_ms = (time.perf_counter() - start) * 1e3
        except Exception as exc:
            traceback.print_exc()
            errors[method] = f"{type(exc).__name__}: {exc}"
            continue
        records[method].append(record_from_result(entry.image_path, result, gt, latency_ms))
    for key, peer in peers.items():
        if key in errors:
            continue
        pipeline = peer["pipelines"][entry.camera_id]
        try:
            start = time.perf_counter()
            plain = pipeline.relocalize(image)
            latency_ms = (time.perf_counter() - start) * 1e3
        except Exception as exc:
            traceback.print_exc()
            errors[key] = f"{type(exc).__name__}: {exc}"
            continue
        records[key].append(record_from_result(entry.image_path, plain_as_reloc(key, plain),
                                               gt, latency_ms))


def plain_as_reloc(method: str, plain: Any) -> RelocResult:
    """A :class:`~.peers.PlainResult` as a :class:`RelocResult`, so that ``reloc eval``'s
    scoring applies to the peer unchanged."""
    timings = dict(plain.timings)
    if plain.ok:
        return RelocResult(status=RelocStatus.OK, method=method,
                           world_from_cam=plain.world_from_cam, inliers=plain.inliers,
                           num_matches=plain.matches, timings=timings)
    return RelocResult.failure(method, f"{plain.inliers} RANSAC inliers of {plain.matches} "
                               "matches", inliers=plain.inliers, num_matches=plain.matches,
                               timings=timings)


def summary_dict(s: Any) -> dict[str, Any]:
    """The figures of one column from ``reloc eval``'s :class:`MethodSummary`."""
    return {"queries": s.queries, "returned": s.relocalized, "recall": dict(s.recall),
            "wrong_rate": s.wrong_rate, "off_rate": s.off_rate,
            "covariance_scale": s.covariance_scale,
            "covariance_rms_scale": s.covariance_rms_scale, "beyond_3_sigma": s.beyond_3_sigma,
            "returned_rate": 1.0 - s.not_relocalized_rate,
            "not_relocalized_rate": s.not_relocalized_rate,
            "median_t_err_m": s.median_t_err_m, "median_r_err_deg": s.median_r_err_deg,
            "p50_ms": s.latency_p50_ms, "p99_ms": s.latency_p99_ms}


# -- running it from the CLI -------------------------------------------------------------------

def run_into(result: dict[str, Any], conf: AccuracyConf, workdir: Path | None) -> None:
    """Run the section into ``result``
    (``result["accuracy"]``, or ``{"error": ...}`` if it failed as a whole) and update the
    run's bookkeeping (section_seconds, conf, duration, load average)."""
    import contextlib
    import tempfile

    from .machine import load_average

    result.setdefault("conf", {})["accuracy"] = json_safe(dataclasses.asdict(conf) | {
        "datasets": [str(d) for d in conf.datasets],
        "real_root": None if conf.real_root is None else str(conf.real_root),
        "cache": None if conf.cache is None else str(conf.cache)})
    say("accuracy ...")
    start = time.perf_counter()
    try:
        with contextlib.ExitStack() as stack:
            tmp = workdir or Path(stack.enter_context(tempfile.TemporaryDirectory(
                prefix="reloc-bench-accuracy-")))
            section = bench_accuracy(conf, tmp)
    except Exception as exc:  # recorded as the other sections record theirs
        traceback.print_exc()
        result["accuracy"] = {"error": f"{type(exc).__name__}: {exc}"}
        section = None
    elapsed = time.perf_counter() - start
    if section is not None:
        result["accuracy"] = json_safe(section)
        result.setdefault("section_seconds", {})["accuracy"] = elapsed
        say(f"accuracy done in {elapsed:.1f} s")
    result["duration_s"] = result.get("duration_s", 0.0) + elapsed
    if isinstance(result.get("machine"), dict):
        result["machine"]["load_average_at_end"] = load_average()
