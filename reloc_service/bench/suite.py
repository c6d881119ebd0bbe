"""The ``reloc bench`` suite: every figure measured side by side in one run, on a synthetic
scene the suite renders itself, against what a user would otherwise use (plain OpenCV) and
against the limit of the work itself (JPEG decode + feature extraction).

:func:`run_suite` returns a plain dict (the JSON ``reloc bench --json`` writes); the CLI
formats it. Sections, each a function of a shared :class:`Workspace`:

- ``latency``: per method, in-process (:class:`Engine`) and over Zenoh on loopback, p50/p99
  and the per-stage breakdown, and the decode + features limit of the same queries;
- ``peers``: the plain OpenCV pipeline (:mod:`.peers`) and PoseLib against
  ``cv2.solvePnPRansac`` on the correspondences our matcher finds;
- ``throughput``: 1, 2, 4, 8 concurrent Zenoh clients;
- ``scaling``: maps of 10, 100, 1000 keyframes (:mod:`.scaling`);
- ``ferns``: the ferns classifier (:mod:`.ferns_bench`);
- ``planar``: micro-benchmarks of the multi relocalizer on a textured plane
  (:mod:`.multi_bench`, full run only).

OpenCV runs on one thread throughout (as each service worker uses one core), so the figures
do not depend on how many cores happen to be free; the load average is recorded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ..cameras import Camera, camera_from_dict
from ..engine import Engine, EngineConf, MappingConf
from ..eval import metrics
from ..features import FeatureConf, extract
from ..frame import Frame
from ..geometry import pose_error
from ..progress import progress
from ..relocalizers.base import RelocResult
from .machine import load_average, machine_record

Array = npt.NDArray[np.float64]

SECTIONS = ("latency", "peers", "throughput", "scaling", "ferns", "planar")
#: Name of the map the loopback services serve, and the camera id queries name.
MAP_NAME = "bench"
CAMERA_ID = "cam0"
JPEG_QUALITY = 90
#: Pose thresholds (metres, degrees) of the headline recall.
HEADLINE_RECALL = "5cm_5deg"


@dataclass(frozen=True)
class Variant:
    """A method as benchmarked: its label, method string, the engine group holding it (one
    engine per plugin options) and the features whose extraction is its limit."""

    label: str
    method: str
    group: str
    limit: str


#: The ORB fast path's options (multi_bench's preset: 500 query features, 3 candidates).
ORB_OPTIONS: dict[str, dict[str, Any]] = {"p3p": {"kind": "orb", "max_features": 500},
                                          "multi": {"num_candidates": 3}}

VARIANTS: tuple[Variant, ...] = (
    Variant("sbi+esm", "sbi+esm", "default", "sift"),
    Variant("sbi+p3p", "sbi+p3p", "default", "sift"),
    Variant("sbi+p3p orb", "sbi+p3p", "orb", "orb"),
    Variant("bow+p3p", "bow+p3p", "default", "sift"),
    Variant("ferns", "ferns", "default", "sift"),
)


@dataclass(frozen=True)
class SuiteConf:
    """Sizes of one run. ``scale`` shrinks the rendered 640x480 images (quick runs)."""

    name: str
    preset: str = "desk"
    scale: float = 1.0
    seed: int = 0
    #: Measured passes over the queries (after one warm-up query per method).
    repeats: int = 5
    ferns_options: Mapping[str, Any] = field(default_factory=dict)
    throughput_clients: tuple[int, ...] = (1, 2, 4, 8)
    throughput_seconds: float = 10.0
    service_workers: int = 2
    service_queue: int = 8
    map_sizes: tuple[int, ...] = (10, 100, 1000)
    unique_distractors: int = 50
    scaling_repeats: int = 2
    scaling_plain_queries: int = 3
    #: Methods probed at every map size. Ferns is left out: its classes are capped per model
    #: (``max_classes``), so its query cost does not grow with keyframes (the ``ferns``
    #: section sweeps classes instead), and training it on the 1000-keyframe map took over
    #: 10 minutes and 12 GB, beyond this benchmark's budget.
    scaling_methods: tuple[str, ...] = ("sbi+esm", "sbi+p3p", "bow+p3p")
    ferns_classes: tuple[int, ...] = (200, 500, 1000, 2000, 5000)
    ferns_warps: int = 100
    ferns_online_landmarks: int = 1000
    ferns_repeats: int = 10
    sections: tuple[str, ...] = SECTIONS

    def __post_init__(self) -> None:
        unknown = sorted(set(self.sections) - set(SECTIONS))
        if unknown:
            raise ValueError(f"unknown bench section(s) {unknown}; expected some of {SECTIONS}")
        if self.repeats < 1 or not self.throughput_clients or not self.map_sizes:
            raise ValueError("repeats >= 1, throughput_clients and map_sizes are required")


QUICK = SuiteConf("quick", scale=0.5, repeats=2, ferns_options={"num_warps": 20},
                  throughput_clients=(1, 2, 4, 8), throughput_seconds=2.0,
                  map_sizes=(10, 40), unique_distractors=6, scaling_repeats=1,
                  scaling_plain_queries=2, ferns_classes=(200, 500), ferns_warps=10,
                  ferns_online_landmarks=200, ferns_repeats=3,
                  sections=tuple(s for s in SECTIONS if s != "planar"))
FULL = SuiteConf("full")


# -- queries -----------------------------------------------------------------------------------

@dataclass(eq=False)
class QuerySet:
    """Query images as the drone sends them (JPEG bytes), their ground-truth
    ``world_from_cam`` and the camera."""

    camera: Camera
    jpegs: list[bytes]
    gts: list[Array]

    def __len__(self) -> int:
        return len(self.jpegs)

    @classmethod
    def from_images(cls, camera: Camera, images: Sequence[npt.NDArray[np.uint8]],
                    gts: Sequence[Array], quality: int = JPEG_QUALITY) -> QuerySet:
        jpegs = []
        for image in images:
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
            if not ok:
                raise ValueError("JPEG encoding failed")
            jpegs.append(buf.tobytes())
        return cls(camera, jpegs, [np.asarray(g, np.float64) for g in gts])

    def save(self, directory: Path) -> Path:
        """Write ``camera.json``, ``gt.npy`` and ``NNNN.jpg`` into ``directory``."""
        import json

        directory.mkdir(parents=True, exist_ok=True)
        (directory / "camera.json").write_text(json.dumps(self.camera.to_dict()))
        np.save(directory / "gt.npy", np.stack(self.gts))
        for i, jpeg in enumerate(self.jpegs):
            (directory / f"{i:04d}.jpg").write_bytes(jpeg)
        return directory

    @classmethod
    def load(cls, directory: Path) -> QuerySet:
        import json

        camera = camera_from_dict(json.loads((directory / "camera.json").read_text()))
        gts = list(np.load(directory / "gt.npy"))
        jpegs = [(directory / f"{i:04d}.jpg").read_bytes() for i in range(len(gts))]
        return cls(camera, jpegs, gts)


def decode_jpeg(jpeg: bytes) -> npt.NDArray[np.uint8]:
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError("query does not decode")
    return np.asarray(image, np.uint8)


def relocalize_jpeg(engine: Engine, jpeg: bytes, camera: Camera, method: str) -> RelocResult:
    """What the service does with a query, in-process: decode, Frame, ``Engine.relocalize``.
    ``timings`` gains ``decode`` and ``wall`` (the whole, seconds)."""
    start = time.perf_counter()
    image = decode_jpeg(jpeg)
    decoded = time.perf_counter()
    result = engine.relocalize(Frame(image, camera), method=method)
    result.timings["decode"] = decoded - start
    result.timings["wall"] = time.perf_counter() - start
    return result


# -- statistics --------------------------------------------------------------------------------

def pct_ms(seconds: Sequence[float], q: float) -> float:
    """The ``q``-th percentile of ``seconds`` in milliseconds (NaN for no value)."""
    values = [s for s in seconds if s is not None and math.isfinite(s)]
    return 1e3 * float(np.percentile(values, q)) if values else math.nan


def stage_medians_ms(timings: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Median milliseconds of every stage over ``timings`` (a missing stage counts 0)."""
    stages = sorted({k for t in timings for k in t})
    return {k: 1e3 * float(np.median([t.get(k, 0.0) for t in timings])) for k in stages}


def accuracy(poses: Sequence[Array | None], gts: Sequence[Array]) -> dict[str, Any]:
    """Recall at the eval thresholds, the rate of returned poses and of wrong ones."""
    t = np.full(len(poses), np.nan)
    r = np.full(len(poses), np.nan)
    ok = np.array([p is not None for p in poses], bool)
    for i, (pose, gt) in enumerate(zip(poses, gts, strict=True)):
        if pose is not None:
            dt, dr = pose_error(pose, gt)
            t[i], r[i] = dt, math.degrees(dr)
    return {"recall": metrics.recalls(t, r, ok), "returned_rate": float(ok.mean()) if len(ok)
            else math.nan, "wrong_rate": metrics.wrong_rate(t, r, ok),
            "median_t_err_m": float(np.nanmedian(t)) if ok.any() else math.nan}


def summarize_samples(samples: Sequence[tuple[int, RelocResult]], queries: QuerySet
                      ) -> dict[str, Any]:
    """p50/p99 of the whole (``wall``), stage medians and accuracy of (query index, result)
    samples from :func:`relocalize_jpeg`."""
    walls = [r.timings["wall"] for _, r in samples]
    return {"samples": len(samples), "p50_ms": pct_ms(walls, 50), "p99_ms": pct_ms(walls, 99),
            "mean_ms": 1e3 * float(np.mean(walls)) if walls else math.nan,
            "stages_ms": stage_medians_ms([r.timings for _, r in samples]),
            **accuracy([r.world_from_cam if r.ok else None for _, r in samples],
                       [queries.gts[i] for i, _ in samples])}


def summarize_plain(samples: Sequence[tuple[int, Any]], queries: QuerySet) -> dict[str, Any]:
    """As :func:`summarize_samples`, for :class:`~.peers.PlainResult` samples."""
    walls = [sum(r.timings.values()) for _, r in samples]
    return {"samples": len(samples), "p50_ms": pct_ms(walls, 50), "p99_ms": pct_ms(walls, 99),
            "stages_ms": stage_medians_ms([r.timings for _, r in samples]),
            "matches_median": float(np.median([r.matches for _, r in samples])) if samples
            else math.nan,
            **accuracy([r.world_from_cam for _, r in samples],
                       [queries.gts[i] for i, _ in samples])}


def json_safe(value: Any) -> Any:
    """``value`` with NumPy scalars as Python numbers and NaN/inf as None (strict JSON)."""
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    return value


def _say(message: str) -> None:
    print(f"[reloc bench] {message}", file=sys.stderr, flush=True)


# -- workspace: the scene, its map, the engines ------------------------------------------------

@dataclass(eq=False)
class Workspace:
    """What every section shares: the queries, one engine per options group (trained, over
    the same map) and each engine's saved map in a service storage folder."""

    conf: SuiteConf
    tmp: Path
    queries: QuerySet
    engines: dict[str, Engine]
    options: dict[str, dict[str, dict[str, Any]]]
    storage: dict[str, Path]
    info: dict[str, Any]

    def methods(self, group: str) -> list[str]:
        return [v.method for v in VARIANTS if v.group == group]


def group_options(conf: SuiteConf) -> dict[str, dict[str, dict[str, Any]]]:
    """Plugin options of each engine group."""
    # Ferns trains online as keyframes arrive; nothing arrives after training here, and
    # Engine.load would otherwise retrain ferns while it feeds the keyframes, before
    # restoring the saved model, which the load times would then include.
    return {"default": {"ferns": {"online": False, **conf.ferns_options}},
            "orb": {k: dict(v) for k, v in ORB_OPTIONS.items()}}


def prepare(conf: SuiteConf, tmp: Path) -> Workspace:
    """Render the scene, build its map (SIFT and ORB landmarks, triangulated), train every
    method, and save each group's engine into a service storage folder."""
    from ..data.dataset import read_dataset
    from ..synth import render_dataset

    info: dict[str, Any] = {"preset": conf.preset, "scale": conf.scale, "seed": conf.seed}
    start = time.perf_counter()
    _say(f"rendering preset {conf.preset!r} at scale {conf.scale}")
    root = render_dataset(conf.preset, tmp / "dataset", seed=conf.seed, scale=conf.scale,
                          progress=True)
    info["render_s"] = time.perf_counter() - start
    ds = read_dataset(root)
    camera = ds.camera(ds.map_entries[0])
    queries = QuerySet.from_images(camera, [ds.load_image(e) for e in ds.query_entries],
                                   [np.array(e.world_from_cam) for e in ds.query_entries])
    options = group_options(conf)
    ws = Workspace(conf, tmp, queries, {}, options, {}, info)
    default = Engine(EngineConf(methods=tuple(ws.methods("default")), options=options["default"],
                                mapping=MappingConf(feature_kinds=("sift", "orb"))))
    start = time.perf_counter()
    for kf_id, entry in progress(list(enumerate(ds.map_entries)), desc="map keyframes"):
        default.add_keyframe(kf_id, ds.load_image(entry), camera, np.array(entry.world_from_cam))
    info["build_s"] = time.perf_counter() - start
    info["train_s"] = {}
    for method in ws.methods("default"):
        start = time.perf_counter()
        default.train([method], progress=True)
        info["train_s"][method] = time.perf_counter() - start
    status = default.status()
    info.update(keyframes=status["keyframes"], landmarks=status["landmarks"],
                queries=len(queries), image=f"{camera.width}x{camera.height}",
                camera_model=camera.model, jpeg_quality=JPEG_QUALITY,
                jpeg_kb_median=float(np.median([len(j) for j in queries.jpegs])) / 1024)
    ws.engines["default"] = default
    ws.storage["default"] = _save_for_service(default, tmp / "storage-default")
    start = time.perf_counter()
    orb = Engine.load(ws.storage["default"] / MAP_NAME / "map",
                      EngineConf(methods=tuple(ws.methods("orb")), options=options["orb"]))
    info["engine_load_s"] = time.perf_counter() - start
    ws.engines["orb"] = orb
    ws.storage["orb"] = _save_for_service(orb, tmp / "storage-orb")
    return ws


def _save_for_service(engine: Engine, storage: Path) -> Path:
    """Save ``engine`` where a service with ``storage`` finds map :data:`MAP_NAME`."""
    from ..service.app import map_dirname

    engine.save(storage / map_dirname(MAP_NAME) / "map")
    return storage


def _service(ws: Workspace, group: str, *, process: bool = False
             ) -> contextlib.AbstractContextManager[str]:
    """The loopback service of ``group``'s saved map (see :mod:`.loopback`)."""
    from .loopback import loopback_service

    return loopback_service(ws.storage[group], ws.methods(group), ws.options[group],
                            map_name=MAP_NAME, workers=ws.conf.service_workers,
                            queue_size=ws.conf.service_queue, process=process)


def _client(endpoint: str, camera: Camera) -> Any:
    """A client on map :data:`MAP_NAME` whose camera :data:`CAMERA_ID` is applied."""
    from .loopback import camera_client

    return camera_client(endpoint, MAP_NAME, CAMERA_ID, camera)


# -- section: latency --------------------------------------------------------------------------

def bench_latency(ws: Workspace) -> dict[str, Any]:
    """Every query by every method, in-process then over Zenoh (the same JPEG bytes), with
    the decode + features limit of the same query measured alongside; repeated
    ``conf.repeats`` times so machine load hits every column alike."""
    q, conf = ws.queries, ws.conf
    with contextlib.ExitStack() as stack:
        clients = {}
        for group in ws.engines:
            endpoint = stack.enter_context(_service(ws, group))
            clients[group] = stack.enter_context(_client(endpoint, q.camera))
        for v in VARIANTS:  # warm-up: first call of each path
            relocalize_jpeg(ws.engines[v.group], q.jpegs[0], q.camera, v.method)
            clients[v.group].relocalize(q.jpegs[0], camera_id=CAMERA_ID, method=v.method)
        limit: dict[str, list[float]] = {"decode": [], "sift": [], "orb": []}
        local: dict[str, list[tuple[int, RelocResult]]] = {v.label: [] for v in VARIANTS}
        remote: dict[str, list[Any]] = {v.label: [] for v in VARIANTS}
        passes = [(r, i) for r in range(conf.repeats) for i in range(len(q))]
        for _, i in progress(passes, desc="latency (queries x repeats)"):
            _measure_limit(q.jpegs[i], limit)
            for v in VARIANTS:
                local[v.label].append((i, relocalize_jpeg(ws.engines[v.group], q.jpegs[i],
                                                          q.camera, v.method)))
                remote[v.label].append(clients[v.group].relocalize(
                    q.jpegs[i], camera_id=CAMERA_ID, method=v.method))
    limits = _limit_summary(limit)
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


def _measure_limit(jpeg: bytes, out: dict[str, list[float]]) -> None:
    """Decode alone, then SIFT (2000, as p3p) and ORB (500, as the ORB path) extraction."""
    start = time.perf_counter()
    image = decode_jpeg(jpeg)
    out["decode"].append(time.perf_counter() - start)
    for kind, n in (("sift", 2000), ("orb", int(ORB_OPTIONS["p3p"]["max_features"]))):
        start = time.perf_counter()
        extract(image, FeatureConf(kind=kind, max_features=n))
        out[kind].append(time.perf_counter() - start)


def _limit_summary(limit: Mapping[str, list[float]]) -> dict[str, float]:
    decode = np.asarray(limit["decode"])
    out = {"decode_p50_ms": pct_ms(limit["decode"], 50)}
    for kind in ("sift", "orb"):
        out[f"{kind}_p50_ms"] = pct_ms(limit[kind], 50)
        out[f"{kind}_limit_p50_ms"] = pct_ms(list(decode + np.asarray(limit[kind])), 50)
        out[f"{kind}_limit_p99_ms"] = pct_ms(list(decode + np.asarray(limit[kind])), 99)
    return out


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
    """The plain OpenCV pipeline against ours (``sbi+p3p``, in-process), query by query in
    turn; and PoseLib against ``cv2.solvePnPRansac`` on the correspondences our matcher
    finds for each query."""
    from .peers import PlainMap, PlainOpenCVPipeline

    q, engine = ws.queries, ws.engines["default"]
    state = engine.map.snapshot()
    plains = {"plain_opencv": PlainOpenCVPipeline(PlainMap.from_state(state), q.camera),
              "plain_opencv_dedup": PlainOpenCVPipeline(PlainMap.from_state(state, dedupe=True),
                                                        q.camera)}
    ours: list[tuple[int, RelocResult]] = []
    theirs: dict[str, list[tuple[int, Any]]] = {k: [] for k in plains}
    for p in plains.values():
        p.relocalize_jpeg(q.jpegs[0])  # warm-up
    passes = [(r, i) for r in range(ws.conf.repeats) for i in range(len(q))]
    for _, i in progress(passes, desc="plain OpenCV vs ours"):
        ours.append((i, relocalize_jpeg(engine, q.jpegs[i], q.camera, "sbi+p3p")))
        for name, p in plains.items():
            theirs[name].append((i, p.relocalize_jpeg(q.jpegs[i])))
    ours_row = summarize_samples(ours, q)
    out: dict[str, Any] = {"ours": {"method": "sbi+p3p", **ours_row}}
    for name, p in plains.items():
        row = summarize_plain(theirs[name], q)
        row["map_descriptors"] = len(p.map)
        row["latency_over_ours"] = row["p50_ms"] / ours_row["p50_ms"]
        out[name] = row
    out["pnp"] = _pnp_on_our_matches(ws)
    return out


def _pnp_on_our_matches(ws: Workspace) -> dict[str, Any]:
    """For each query: the SIFT matches ``sbi+p3p`` finds (its top candidates, its ratio
    test), then PoseLib and OpenCV RANSAC on them (:func:`multi_bench.compare_pnp`)."""
    from ..pose.p3p import P3PPoseFinder
    from ..relocalizers.multi import MultiRelocalizer
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


# -- section: throughput -----------------------------------------------------------------------

def bench_throughput(ws: Workspace, method: str = "sbi+p3p") -> dict[str, Any]:
    """Queries per second and latency with 1, 2, 4, 8 concurrent clients (each its own Zenoh
    session, querying back to back with the JPEG queries) against one service with
    ``service_workers`` workers; "busy" replies are counted apart."""
    conf, q = ws.conf, ws.queries
    runs = []
    with _service(ws, "default", process=True) as endpoint:
        with _client(endpoint, q.camera) as client:
            client.relocalize(q.jpegs[0], camera_id=CAMERA_ID, method=method)  # warm-up
        for n in progress(list(conf.throughput_clients), desc="throughput (client counts)"):
            runs.append(_throughput_run(endpoint, q, method, n, conf.throughput_seconds))
    base = runs[0]["queries_per_s"]
    for row in runs:
        row["speedup_over_first"] = row["queries_per_s"] / base if base else math.nan
    return {"method": method, "workers": conf.service_workers, "queue_size": conf.service_queue,
            "duration_s": conf.throughput_seconds, "runs": runs,
            "in_process_threads": _in_process_threads(ws, method, conf.throughput_seconds),
            "note": "clients are threads of the benchmark process, each with its own Zenoh "
                    "session; the service is `reloc serve` in its own process, as deployed"}


def _in_process_threads(ws: Workspace, method: str, duration_s: float,
                        threads: Sequence[int] = (1, 2)) -> list[dict[str, Any]]:
    """Queries per second of 1 and 2 threads querying one engine back to back, no Zenoh:
    how far the work itself lets two workers use two cores (OpenCV, NumPy and PoseLib
    release the GIL; the Python between them does not)."""
    q, engine = ws.queries, ws.engines["default"]
    rows = []
    for n in threads:
        done = [0] * n
        deadline = time.perf_counter() + duration_s

        def work(k: int, done: list[int] = done, deadline: float = deadline) -> None:
            i = k
            while time.perf_counter() < deadline:
                relocalize_jpeg(engine, q.jpegs[i % len(q)], q.camera, method)
                done[k] += 1
                i += 1

        start = time.perf_counter()
        pool = [threading.Thread(target=work, args=(k,)) for k in range(n)]
        for t in pool:
            t.start()
        for t in pool:
            t.join()
        rows.append({"threads": n, "queries_per_s": sum(done) / (time.perf_counter() - start)})
    return rows


def _throughput_run(endpoint: str, q: QuerySet, method: str, n: int, duration_s: float
                    ) -> dict[str, Any]:
    from reloc_client.client import RelocClient, ServiceBusy

    counts = {"ok": 0, "not_relocalized": 0, "busy": 0}
    latencies: list[float] = []
    lock = threading.Lock()
    barrier = threading.Barrier(n + 1)
    errors: list[str] = []

    def client_loop(index: int) -> None:
        with RelocClient(endpoint, map=MAP_NAME, timeout=120) as c:
            barrier.wait()
            deadline = time.perf_counter() + duration_s
            i = index
            while time.perf_counter() < deadline:
                try:
                    r = c.relocalize(q.jpegs[i % len(q)], camera_id=CAMERA_ID, method=method)
                except ServiceBusy:
                    with lock:
                        counts["busy"] += 1
                    time.sleep(0.005)
                    continue
                except Exception as exc:  # reported, not hidden
                    errors.append(f"{type(exc).__name__}: {exc}")
                    return
                i += 1
                with lock:
                    counts["ok" if r.ok else "not_relocalized"] += 1
                    latencies.append(r.round_trip_s or math.nan)

    threads = [threading.Thread(target=client_loop, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    barrier.wait()
    start = time.perf_counter()
    for t in threads:
        t.join()
    elapsed = time.perf_counter() - start
    if errors:
        raise RuntimeError(f"throughput with {n} clients: {errors[0]}")
    answered = counts["ok"] + counts["not_relocalized"]
    return {"clients": n, "queries_per_s": answered / elapsed, "answered": answered, **counts,
            "p50_ms": pct_ms(latencies, 50), "p99_ms": pct_ms(latencies, 99)}


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
                   "(noise at four scales and random shapes) with real SIFT features, "
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
        h["throughput"] = {"clients": [first["clients"], last["clients"]],
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


def run_suite(conf: SuiteConf, *, command: str = "", workdir: Path | None = None
              ) -> dict[str, Any]:
    """Run the sections of ``conf``; a failing section is recorded (``{"error": ...}``) and
    the others still run. Returns the JSON-ready result."""
    started = time.perf_counter()
    result: dict[str, Any] = {
        "schema": "reloc-bench/1", "command": command, "suite": conf.name,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "conf": json_safe(dataclasses.asdict(conf)), "machine": machine_record()}
    cv2.setNumThreads(1)
    with contextlib.ExitStack() as stack:
        tmp = workdir or Path(stack.enter_context(tempfile.TemporaryDirectory(
            prefix="reloc-bench-")))
        needs_scene = {"latency", "peers", "throughput", "scaling"} & set(conf.sections)
        ws = None
        if needs_scene:
            ws = _run_section(result, "scene", lambda: prepare(conf, tmp))
            if ws is not None:
                result["scene"] = json_safe(ws.info)
        steps: dict[str, Callable[[], dict[str, Any]]] = {
            "latency": lambda: bench_latency(ws),  # type: ignore[arg-type]
            "peers": lambda: bench_peers(ws),  # type: ignore[arg-type]
            "throughput": lambda: bench_throughput(ws),  # type: ignore[arg-type]
            "scaling": lambda: bench_scaling(ws),  # type: ignore[arg-type]
            "ferns": lambda: bench_ferns(conf),
            "planar": lambda: bench_planar(conf)}
        for name in conf.sections:
            if name in needs_scene and ws is None:
                result[name] = {"error": "skipped: the scene could not be prepared"}
                continue
            section = _run_section(result, name, steps[name])
            if section is not None:
                result[name] = json_safe(section)
    result["headline"] = json_safe(headline(result))
    result["machine"]["load_average_at_end"] = load_average()
    result["duration_s"] = time.perf_counter() - started
    return json_safe(result)


def _run_section(result: dict[str, Any], name: str, fn: Callable[[], Any]) -> Any:
    """``fn()`` timed; on an exception, ``result[name]`` records it and None is returned."""
    _say(f"{name} ...")
    start = time.perf_counter()
    try:
        value = fn()
    except Exception as exc:  # one failing section must not lose the others' figures
        traceback.print_exc()
        result[name] = {"error": f"{type(exc).__name__}: {exc}"}
        return None
    result.setdefault("section_seconds", {})[name] = time.perf_counter() - start
    _say(f"{name} done in {time.perf_counter() - start:.1f} s")
    return value


def failed_sections(result: Mapping[str, Any]) -> list[str]:
    """Names of the sections that recorded an error."""
    return [k for k, v in result.items() if isinstance(v, Mapping) and "error" in v]
