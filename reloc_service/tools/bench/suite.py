"""The ``reloc bench`` suite: every figure measured side by side in one run, on a synthetic
scene the suite renders itself, against what a user would otherwise use (plain OpenCV) and
against the limit of the work itself (JPEG decode + feature extraction).

:func:`run_suite` returns a plain dict (the JSON ``reloc bench --json`` writes); the CLI
formats it. Sections, each a function of a shared :class:`~.workspace.Workspace` (the scene,
its trained engines, the run's sizes; measurement helpers in :mod:`.samples`):

- ``latency``: per method (the service's default method first, labelled ``default``),
  in-process (:class:`Engine`) and over Zenoh on loopback, p50/p99 and the per-stage
  breakdown, and the decode + features limit of the same queries;
- ``peers``: the plain OpenCV pipeline (:mod:`.peers`) against the default method and
  ``sbi+p3p``, and PoseLib against ``cv2.solvePnPRansac`` on the correspondences our
  matcher finds;
- ``throughput``: 1, 2, 4, 8 concurrent Zenoh clients against ``reloc serve`` with the
  default method, per worker mode (process, thread) the service knows (:mod:`.throughput`);
- ``scaling``: maps of 10, 100, 1000 keyframes (:mod:`.scaling`);
- ``ferns``: the ferns classifier (:mod:`.ferns_bench`);
- ``planar``: micro-benchmarks of the multi relocalizer on a textured plane
  (:mod:`.multi_bench`, full run only);
- ``intrinsics``: the intrinsics test alone on synthetic correspondences
  (:mod:`.intrinsics_bench`).

The CLI adds ``accuracy`` (:mod:`.accuracy`: the presets and the real sets, run by every
whole run) and, only when named with ``--only``, ``soak``, the reliability soak run with
kill -9 / SIGTERM restarts (:mod:`.soak`); then the targets table (:mod:`.targets`).

OpenCV runs on one thread throughout (as each service worker uses one core), so the figures
do not depend on how many cores happen to be free; the load average is recorded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import tempfile
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...algorithms.relocalizers.base import RelocResult
from ...algorithms.relocalizers.factory import DEFAULT_METHOD
from ...core.frame import Frame
from ...core.numeric import limit_blas_threads
from ...core.progress import progress
from ...engine import EngineConf
from ..eval.results import json_safe
from .limit import limit_summary, measure_limit
from .machine import code_record, load_average, machine_record
from .samples import (
    JPEG_QUALITY,
    decode_jpeg,
    pct_ms,
    relocalize_jpeg,
    stage_medians_ms,
    summarize_plain,
    summarize_samples,
)
from .throughput import bench_throughput
from .workspace import (
    CAMERA_ID,
    FULL,
    HEADLINE_RECALL,
    ORB_OPTIONS,
    QUICK,
    SECTIONS,
    VARIANTS,
    SuiteConf,
    Workspace,
    group_client,
    group_service,
    prepare,
    say,
)

__all__ = ["FULL", "QUICK", "SECTIONS", "SuiteConf", "failed_sections", "run_suite"]


# -- section: latency --------------------------------------------------------------------------

def bench_latency(ws: Workspace) -> dict[str, Any]:
    """Every query by every method, in-process then over Zenoh (the same JPEG bytes), with
    the decode + features limit of the same query measured alongside; repeated
    ``conf.repeats`` times so machine load hits every column alike."""
    q, conf = ws.queries, ws.conf
    with contextlib.ExitStack() as stack:
        clients = {}
        for group in ws.engines:
            endpoint = stack.enter_context(group_service(ws, group))
            clients[group] = stack.enter_context(group_client(endpoint, q.camera))
        for v in VARIANTS:  # warm-up: first call of each path
            relocalize_jpeg(ws.engines[v.group], q.jpegs[0], q.camera, v.method)
            clients[v.group].relocalize(q.jpegs[0], camera_id=CAMERA_ID, method=v.method)
        limit: dict[str, list[float]] = {"decode": [], "sift": [], "orb": []}
        local: dict[str, list[tuple[int, RelocResult]]] = {v.label: [] for v in VARIANTS}
        remote: dict[str, list[Any]] = {v.label: [] for v in VARIANTS}
        passes = [(r, i) for r in range(conf.repeats) for i in range(len(q))]
        for _, i in progress(passes, desc="latency (queries x repeats)"):
            measure_limit(functools.partial(decode_jpeg, q.jpegs[i]), limit, LIMIT_COUNTS)
            for v in VARIANTS:
                local[v.label].append((i, relocalize_jpeg(ws.engines[v.group], q.jpegs[i],
                                                          q.camera, v.method)))
                remote[v.label].append(clients[v.group].relocalize(
                    q.jpegs[i], camera_id=CAMERA_ID, method=v.method))
    limits = limit_summary(limit)
    methods = {}
    for v in VARIANTS:
        row = summarize_samples(local[v.label], q)
        row.update(method=v.method, options=ws.options[v.group] if v.group != "default"
                   else {}, limit=v.limit,
                   over_limit=row["p50_ms"] / limits[f"{v.limit}_limit_p50_ms"],
                   over_sift_limit=row["p50_ms"] / limits["sift_limit_p50_ms"],
                   zenoh=_remote_summary(remote[v.label], local[v.label]))
        methods[v.label] = row
    return {"queries": len(q), "repeats": conf.repeats, "limit": limits, "methods": methods,
            "service": {"workers": conf.service_workers, "queue_size": conf.service_queue,
                        "image_on_wire": f"JPEG quality {JPEG_QUALITY}"}}


#: The limit's extractions: SIFT (2000, as p3p) and ORB (500, as the ORB path).
LIMIT_COUNTS: dict[str, int] = {"sift": 2000, "orb": int(ORB_OPTIONS["p3p"]["max_features"])}


def _remote_summary(replies: Sequence[Any], local: Sequence[tuple[int, RelocResult]]
                    ) -> dict[str, Any]:
    """Round trips (client clock), the service's own total, and the paired difference to the
    in-process run of the same query."""
    trips = [r.round_trip_s for r in replies]
    server = [r.timings.get("total", math.nan) for r in replies]
    added = [t - lr.timings["wall"] for t, (_, lr) in zip(trips, local, strict=True)]
    return {"p50_ms": pct_ms(trips, 50), "p99_ms": pct_ms(trips, 99),
            "server_total_p50_ms": pct_ms(server, 50),
            "transport_p50_ms": pct_ms([t - s for t, s in zip(trips, server, strict=True)], 50),
            "added_over_in_process_p50_ms": pct_ms(added, 50),
            "server_stages_ms": stage_medians_ms([r.timings for r in replies]),
            "ok_rate": float(np.mean([r.ok for r in replies])) if replies else math.nan}


# -- section: peers ----------------------------------------------------------------------------

def bench_peers(ws: Workspace) -> dict[str, Any]:
    """The plain OpenCV pipeline against ours (the default method, and ``sbi+p3p``, the SIFT
    path; in-process), query by query in turn; and PoseLib against ``cv2.solvePnPRansac`` on
    the correspondences our matcher finds for each query. ``latency_over_ours`` is each
    row's p50 over the default method's."""
    from .peers import PlainMap, PlainOpenCVPipeline

    q, engine = ws.queries, ws.engines["default"]
    state = engine.map.snapshot()
    plains = {"plain_opencv": PlainOpenCVPipeline(PlainMap.from_state(state), q.camera),
              "plain_opencv_dedup": PlainOpenCVPipeline(PlainMap.from_state(state, dedupe=True),
                                                        q.camera)}
    mine = {"ours": DEFAULT_METHOD, "ours_sift": "sbi+p3p"}
    ours: dict[str, list[tuple[int, RelocResult]]] = {k: [] for k in mine}
    theirs: dict[str, list[tuple[int, Any]]] = {k: [] for k in plains}
    for p in plains.values():
        p.relocalize_jpeg(q.jpegs[0])  # warm-up
    passes = [(r, i) for r in range(ws.conf.repeats) for i in range(len(q))]
    for _, i in progress(passes, desc="plain OpenCV vs ours"):
        for key, method in mine.items():
            ours[key].append((i, relocalize_jpeg(engine, q.jpegs[i], q.camera, method)))
        for name, p in plains.items():
            theirs[name].append((i, p.relocalize_jpeg(q.jpegs[i])))
    out: dict[str, Any] = {}
    for key, method in mine.items():
        out[key] = {"method": method, **summarize_samples(ours[key], q)}
    base = out["ours"]["p50_ms"]
    out["ours_sift"]["latency_over_ours"] = out["ours_sift"]["p50_ms"] / base
    for name, p in plains.items():
        row = summarize_plain(theirs[name], q)
        row["map_descriptors"] = len(p.map)
        row["latency_over_ours"] = row["p50_ms"] / base
        out[name] = row
    out["pnp"] = _pnp_on_our_matches(ws)
    return out


def _pnp_on_our_matches(ws: Workspace) -> dict[str, Any]:
    """For each query: the SIFT matches ``sbi+p3p`` finds (its top candidates, its ratio
    test), then PoseLib and OpenCV RANSAC on them (:func:`multi_bench.compare_pnp`)."""
    from ...algorithms.pose.p3p import P3PPoseFinder
    from ...algorithms.relocalizers.multi import MultiRelocalizer
    from .multi_bench import compare_pnp, one_cv_thread

    q = ws.queries
    reloc = ws.engines["default"].relocalizer("sbi+p3p")
    assert isinstance(reloc, MultiRelocalizer) and isinstance(reloc.pose, P3PPoseFinder)
    state = ws.engines["default"].map.snapshot()
    rows = []
    with one_cv_thread():
        for i in progress(range(len(q)), desc="PoseLib vs OpenCV RANSAC"):
            frame = Frame(decode_jpeg(q.jpegs[i]), q.camera)
            candidates = reloc.place.find_places(frame, reloc.group_size)
            keyframes = [state.keyframes[c.keyframe_id] for c in candidates]
            feats = reloc.pose.query_features(frame, {})
            q_idx, pool_rows, pool = reloc.pose.match_landmarks(feats, keyframes)
            if len(q_idx) < 6:
                continue
            rows.append(compare_pnp(feats.keypoints_px[q_idx], pool.points_world[pool_rows],
                                    q.camera, q.gts[i], max(3, ws.conf.repeats)))
    if not rows:
        return {"queries": 0}

    def med(key: str) -> float:
        return float(np.median([r[key] for r in rows]))

    def err(side: str, key: str) -> float:
        values = [r[side][key] for r in rows if r[side][key] is not None]
        return float(np.median(values)) if values else math.nan

    return {"queries": len(rows), "correspondences_median": med("correspondences"),
            "poselib_ms_median": med("poselib_ms"), "opencv_ms_median": med("opencv_ms"),
            "solve_pnp_ms_median": med("solve_pnp_ms"),
            "opencv_over_poselib": med("opencv_ms") / med("poselib_ms"),
            "inlier_ratio_median": float(np.median([
                (r["inliers"] or 0) / r["correspondences"] for r in rows])),
            "poselib_t_err_m_median": err("poselib", "error_m"),
            "opencv_t_err_m_median": err("opencv", "error_m"),
            "poselib_failures": sum(r["poselib"]["error_m"] is None for r in rows),
            "opencv_failures": sum(r["opencv"]["error_m"] is None for r in rows)}


# -- section: scaling --------------------------------------------------------------------------

def bench_scaling(ws: Workspace) -> dict[str, Any]:
    """Maps of ``conf.map_sizes`` keyframes: the real map grown with distractor keyframes
    (:func:`scaling.grow_state`); each saved with trained models, then probed in a fresh
    process (memory, load time, latency per method, place-finder time, plain OpenCV)."""
    from . import scaling

    conf, q = ws.conf, ws.queries
    base = ws.engines["default"].map.snapshot()
    methods = list(conf.scaling_methods)
    queries_dir = q.save(ws.tmp / "queries")
    per_kf = scaling.landmarks_per_keyframe(base)
    largest = max(conf.map_sizes)
    unique = min(conf.unique_distractors, max(0, largest - len(base.keyframes)))
    start = time.perf_counter()
    distractors = scaling.make_distractors(unique, q.camera, per_kf, seed=conf.seed)
    made_s = time.perf_counter() - start
    rows = []
    for size in progress(list(conf.map_sizes), desc="map sizes"):
        try:
            rows.append(_scaling_row(ws, base, size, distractors, queries_dir))
        except Exception as exc:  # the other sizes' figures still count
            traceback.print_exc()
            rows.append({"size": size, "error": f"{type(exc).__name__}: {exc}"})
    return {"methods": methods, "base_keyframes": len(base.keyframes),
            "base_landmarks": len(base.landmarks), "unique_distractors": unique,
            "distractor_landmarks_per_keyframe": per_kf, "distractors_made_s": made_s,
            "how": "the real map (rendered keyframes, triangulated landmarks) plus distractor "
                   "keyframes far from the scene: procedural textures of the camera's size "
                   "(noise at four scales and random shapes) sent as JPEG (quality "
                   f"{JPEG_QUALITY}, as a client sends keyframes; the map keeps those bytes) "
                   "with real SIFT features, "
                   f"{per_kf} of them per keyframe given landmarks at random depths of 1-4 m "
                   f"(the real keyframes' median); {unique} unique distractors are rendered and "
                   "repeated at new poses with new landmark ids; each map is saved with its "
                   "trained models and probed in a fresh process",
            "sizes": rows}


def _scaling_row(ws: Workspace, base: Any, size: int, distractors: Any, queries_dir: Path
                 ) -> dict[str, Any]:
    """Grow, train and save the map of ``size`` keyframes, then probe it."""
    from . import scaling

    methods = list(ws.conf.scaling_methods)
    options = {k: v for k, v in ws.options["default"].items() if k != "ferns"}
    # Every size, the scene's own map included, is saved, loaded, trained with the same
    # methods and saved again, so that memory, snapshot and load columns compare alike.
    state = scaling.grow_state(base, size, distractors, ws.queries.camera)
    directory = ws.tmp / f"scaling-{size}"
    row = {"size": size, **scaling.prepare_size(
        state, EngineConf(methods=tuple(methods), options=options), directory)}
    del state
    map_dir = directory / "map"
    row.update(scaling.run_probe(map_dir, queries_dir, methods, options,
                                 repeats=ws.conf.scaling_repeats,
                                 plain_queries=ws.conf.scaling_plain_queries))
    return row


# -- sections: ferns and planar ----------------------------------------------------------------

def bench_ferns(conf: SuiteConf) -> dict[str, Any]:
    """The ferns benchmarks of :mod:`.ferns_bench` at this run's sizes: one model trained
    with the largest class count (training time, memory), classification time of 500
    keypoints for each class count (a subset of that model), and an online keyframe add."""
    from . import ferns_bench

    largest = max(conf.ferns_classes)
    sweep = ferns_bench.bench_classes_sweep(conf.ferns_classes, 500, conf.ferns_warps,
                                            conf.ferns_repeats)
    return {"train": ferns_bench.bench_train(largest, conf.ferns_warps),
            "memory": ferns_bench.bench_memory(largest, conf.ferns_warps),
            "classes_sweep": sweep,
            "online_add": ferns_bench.bench_online_add(conf.ferns_online_landmarks,
                                                       conf.ferns_warps)}


def bench_planar(conf: SuiteConf) -> dict[str, Any]:
    """:func:`multi_bench.run`: the SIFT and ORB paths, SBI over 1000 keyframes and PoseLib
    against OpenCV with added outliers, on a textured plane rendered by homography."""
    from . import multi_bench

    return multi_bench.run(quick=conf.name != "full")


def bench_intrinsics(conf: SuiteConf) -> dict[str, Any]:
    """:func:`intrinsics_bench.run`: the intrinsics test alone, per correspondence count."""
    from . import intrinsics_bench

    return intrinsics_bench.run(repeats=10 if conf.name == "quick" else 30)


# -- the whole run -----------------------------------------------------------------------------

def headline(result: Mapping[str, Any]) -> dict[str, Any]:
    """The ratios quoted first, each from figures of this run (None where a section is
    missing or failed)."""
    h: dict[str, Any] = {}
    lat = result.get("latency", {})
    if "methods" in lat:
        h["over_decode_plus_features"] = {k: m["over_limit"] for k, m in lat["methods"].items()}
        h["p50_ms"] = {k: m["p50_ms"] for k, m in lat["methods"].items()}
        h["zenoh_p50_ms"] = {k: m["zenoh"]["p50_ms"] for k, m in lat["methods"].items()}
        h["decode_plus_sift_p50_ms"] = lat["limit"]["sift_limit_p50_ms"]
    peers = result.get("peers", {})
    if "plain_opencv" in peers:
        h["plain_opencv_latency_over_ours"] = peers["plain_opencv"]["latency_over_ours"]
        h["plain_opencv_dedup_latency_over_ours"] = \
            peers["plain_opencv_dedup"]["latency_over_ours"]
        h["recall_ours"] = peers["ours"]["recall"].get(HEADLINE_RECALL)
        h["recall_plain_opencv"] = peers["plain_opencv"]["recall"].get(HEADLINE_RECALL)
        h["recall_plain_opencv_dedup"] = peers["plain_opencv_dedup"]["recall"].get(
            HEADLINE_RECALL)
        h["opencv_ransac_over_poselib"] = peers.get("pnp", {}).get("opencv_over_poselib")
    thr = result.get("throughput", {})
    if thr.get("runs"):
        first, last = thr["runs"][0], thr["runs"][-1]
        every = [x for runs in (thr.get("modes") or {"": thr["runs"]}).values() for x in runs]
        h["throughput"] = {"method": thr.get("method"), "workers": thr.get("workers"),
                           "mode": thr.get("mode", "thread"),
                           "busy": sum(x.get("busy", 0) for x in every),
                           "lost": sum(x.get("lost", 0) for x in every),
                           "clients": [first["clients"], last["clients"]],
                           "queries_per_s": [first["queries_per_s"], last["queries_per_s"]],
                           "ratio": last["queries_per_s"] / first["queries_per_s"]
                           if first["queries_per_s"] else None,
                           "p99_ms": [first["p99_ms"], last["p99_ms"]]}
    sc = result.get("scaling", {})
    measured = [r for r in sc.get("sizes", []) if "error" not in r]
    if measured:
        big = measured[-1]
        h["largest_map"] = {"keyframes": big["keyframes"], "landmarks": big["landmarks"],
                            "map_rss_mb": big.get("map_rss_mb"),
                            "engine_load_s": big.get("engine_load_s"),
                            "p50_ms": {m: r["p50_ms"] for m, r in big["methods"].items()}}
    return h


def run_suite(conf: SuiteConf, *, command: str = "", workdir: Path | None = None,
              cache: Path | None = None,
              checkpoint: Callable[[Mapping[str, Any]], None] | None = None
              ) -> dict[str, Any]:
    """Run the sections of ``conf``; a failing section is recorded (``{"error": ...}``) and
    the others still run. ``checkpoint`` is called with the result so far after every
    section (so that an interrupted run keeps what it measured). Returns the JSON-ready
    result."""
    started = time.perf_counter()
    cv2.setNumThreads(1)
    limit_blas_threads(1)   # as a service worker runs its queries (one OpenCV, one BLAS thread)
    result: dict[str, Any] = {
        "schema": "reloc-bench/1", "command": command, "suite": conf.name,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "conf": json_safe(dataclasses.asdict(conf)), "machine": machine_record(),
        "code": code_record()}
    with contextlib.ExitStack() as stack:
        tmp = workdir or Path(stack.enter_context(tempfile.TemporaryDirectory(
            prefix="reloc-bench-")))
        needs_scene = {"latency", "peers", "throughput", "scaling"} & set(conf.sections)
        ws = None
        if needs_scene:
            ws = _run_section(result, "scene", lambda: prepare(conf, tmp, cache))
            if ws is not None:
                result["scene"] = json_safe(ws.info)
        steps: dict[str, Callable[[], dict[str, Any]]] = {
            "latency": lambda: bench_latency(ws),  # type: ignore[arg-type]
            "peers": lambda: bench_peers(ws),  # type: ignore[arg-type]
            "throughput": lambda: bench_throughput(ws),  # type: ignore[arg-type]
            "scaling": lambda: bench_scaling(ws),  # type: ignore[arg-type]
            "ferns": lambda: bench_ferns(conf),
            "planar": lambda: bench_planar(conf),
            "intrinsics": lambda: bench_intrinsics(conf)}
        for name in conf.sections:
            if name in needs_scene and ws is None:
                result[name] = {"error": "skipped: the scene could not be prepared"}
                continue
            section = _run_section(result, name, steps[name])
            if section is not None:
                result[name] = json_safe(section)
            if checkpoint is not None:
                checkpoint(json_safe(result))
    result["headline"] = json_safe(headline(result))
    result["machine"]["load_average_at_end"] = load_average()
    result["duration_s"] = time.perf_counter() - started
    return json_safe(result)


def _run_section(result: dict[str, Any], name: str, fn: Callable[[], Any]) -> Any:
    """``fn()`` timed; on an exception, ``result[name]`` records it and None is returned."""
    say(f"{name} ...")
    start = time.perf_counter()
    try:
        value = fn()
    except Exception as exc:  # one failing section must not lose the others' figures
        traceback.print_exc()
        result[name] = {"error": f"{type(exc).__name__}: {exc}"}
        return None
    result.setdefault("section_seconds", {})[name] = time.perf_counter() - start
    say(f"{name} done in {time.perf_counter() - start:.1f} s")
    return value


def failed_sections(result: Mapping[str, Any]) -> list[str]:
    """Names of the sections that recorded an error."""
    return [k for k, v in result.items() if isinstance(v, Mapping) and "error" in v]
