"""Evaluate relocalization methods on a reloc dataset: build the map from ``map.txt``, train,
relocalize every query and score it against its ground truth (thesis chapter 5).

:func:`evaluate` returns an :class:`EvalResult`; printing, JSON and plots are the callers'
(``reloc eval`` formats it with :mod:`.report` and :mod:`.plots`). Where the work runs is a
:class:`~.backends.Backend`: :class:`InProcessBackend` (an :class:`~reloc_service.engine.Engine`
in this process) or a remote one reached through the service (:mod:`.remote`).
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Iterable, Mapping, Sequence
from contextlib import nullcontext
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ... import __version__
from ...algorithms.relocalizers.base import RelocResult, position_sigma_m
from ...core.errors import ConfigError, DatasetError
from ...core.geometry import pose_covariance_from_sigmas, pose_error, pose_to_tum
from ...core.progress import progress as progress_bar
from ..data.dataset import Dataset, DatasetEntry, read_dataset
from . import gt as _gt  # noqa: F401 (importing it registers the ground-truth place finder)
from . import metrics
from .backends import Backend, LandmarkSource, RemoteSpec
from .inprocess import InProcessBackend, as_a_service_worker
from .query_camera import QueryCamera
from .results import EvalResult, MapInfo, MethodResult, MethodSummary, QueryRecord, json_safe

Array = npt.NDArray[np.float64]

#: Distributions whose versions are recorded with every run.
_LIBRARIES = ("numpy", "scipy", "opencv-python-headless", "poselib", "eclipse-zenoh", "msgpack",
              "scikit-image")


# -- the evaluation --------------------------------------------------------------------------

def evaluate(dataset_root: str | Path, method: str | Sequence[str], *,
             options: Mapping[str, Any] | None = None,
             landmarks: LandmarkSource | str = LandmarkSource.AUTO,
             progress: bool = True, remote: RemoteSpec | None = None,
             keyframe_sigma: tuple[float, float] | None = (0.0, 0.0),
             query_camera: QueryCamera | None = None,
             round_trip: bool = False,
             calibration_sigma: tuple[float, float] | None = None) -> EvalResult:
    """Build the map of ``dataset_root``, train, and score every query with each method.

    Args:
        dataset_root: a reloc dataset v1 folder with ``queries.txt``.
        method: a method string (``"gt+none"``, ``"sbi+p3p"``, a fallback chain
            ``"bow+p3p,sbi+esm"``) or several, evaluated on one shared map.
        options: plugin name -> option dict (as in the service config); ``"mapping"`` holds
            the map-building options.
        landmarks: ``auto`` (default: depth where the dataset gives it, triangulation
            elsewhere), ``triangulate`` or ``depth`` (see :class:`LandmarkSource`).
        progress: draw progress bars on stderr.
        remote: run through a service instead of in-process.
        keyframe_sigma: (metres, degrees), the 1-sigma accuracy per axis of the dataset's
            ground-truth poses: every keyframe is put with that pose covariance (what a
            relocalized pose inherits from the map) and every query's ground truth is
            taken as that uncertain when its error is weighed by the stated covariance
            (:func:`.metrics.translation_mahalanobis`). (0, 0): exact poses. None: the
            keyframes are put without a covariance, so the map states its default (the
            mapping options', by default measured from the map itself:
            :mod:`~reloc_service.algorithms.pose.keyframe_disagreement`), and each query's
            ground truth is taken as exact.
        query_camera: what the queries claim about their camera (default: the dataset's);
            the map is built with the dataset's.
        round_trip: query the map as a service restores it: saved after training as a
            service's snapshot stores it by default (:class:`.keyframe_parts.StoredParts`:
            no depth, landmark keypoints only, ...) and loaded back (in-process only).
        calibration_sigma: (relative focal, radial pixels at the farthest image corner), the
            1-sigma accuracy of the dataset's camera calibration, which the map states and
            its answers' covariance carries (``options["mapping"]``'s
            ``calibration_focal_sigma_rel`` / ``calibration_radial_sigma_px``); (0, 0): exact;
            None: the dataset's own ``calibration.json`` (``reloc synth`` states 0, 0) in
            process, else the mapping options' (their default 0.005, 2); a remote service's
            maps state what its configuration says.
    """
    methods = _method_list(method)
    claimed = query_camera or QueryCamera()
    source = LandmarkSource(landmarks)
    truth_covariance = None if keyframe_sigma is None else ground_truth_covariance(keyframe_sigma)
    dataset = read_dataset(dataset_root)
    _check_dataset(dataset, source)
    # A service's maps take their mapping options from its own configuration, not from here.
    stated = None if remote is not None else dataset.calibration_sigma
    options = with_calibration_sigma(options, calibration_to_state(calibration_sigma, options,
                                                                   stated))
    backend = _make_backend(methods, dict(options or {}), source, remote)
    try:
        build_s = _build_map(backend, dataset, source, progress, truth_covariance)
        train_s = _timed(lambda: backend.train(progress=progress))
        if round_trip:
            if not isinstance(backend, InProcessBackend):
                raise ConfigError("a snapshot round trip needs the in-process backend (a "
                                  "service's map is already its own snapshot's)")
            backend.round_trip()
        with as_a_service_worker() if isinstance(backend, InProcessBackend) else nullcontext():
            results = [_evaluate_method(backend, dataset, m, progress, claimed,
                                        truth_covariance)
                       for m in methods]
        map_info = _map_info(backend, dataset, source, build_s, train_s)
    finally:
        backend.close()
    return EvalResult(dataset=_dataset_info(dataset, claimed), map=map_info, methods=results,
                      machine=machine_info(), backend=backend.description,
                      options=json_safe(dict(options or {})),
                      created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
                      ground_truth_sigma=(0.0, 0.0) if keyframe_sigma is None
                      else (float(keyframe_sigma[0]), float(keyframe_sigma[1])))


#: The mapping options that state the map's calibration accuracy.
CALIBRATION_OPTION_KEYS = ("calibration_focal_sigma_rel", "calibration_radial_sigma_px")


def calibration_to_state(given: tuple[float, float] | None, options: Mapping[str, Any] | None,
                       dataset_states: tuple[float, float] | None
                       ) -> tuple[float, float] | None:
    """The calibration accuracy the map states, first found of: the caller's, the mapping
    options' own (None: they stand), the dataset's ``calibration.json``."""
    mapping = dict((options or {}).get("mapping") or {})
    if given is not None or any(key in mapping for key in CALIBRATION_OPTION_KEYS):
        return given
    return dataset_states


def options_stating_dataset_calibration(options: Mapping[str, Any] | None, dataset: Dataset
                                        ) -> Mapping[str, Any] | None:
    """``options`` with the calibration accuracy the map states as ``reloc eval`` sets it
    without ``--calibration-sigma``: the options' own, else the dataset's
    ``calibration.json`` (a rendered set states its camera exact)."""
    return with_calibration_sigma(options, calibration_to_state(None, options,
                                                                dataset.calibration_sigma))


def with_calibration_sigma(options: Mapping[str, Any] | None,
                           calibration_sigma: tuple[float, float] | None
                           ) -> Mapping[str, Any] | None:
    """``options`` with ``calibration_sigma`` (relative focal, radial pixels) set as the
    mapping table's calibration accuracy (unchanged when None); ConfigError unless both are
    finite and >= 0."""
    if calibration_sigma is None:
        return options
    focal_rel, radial_px = (float(v) for v in calibration_sigma)
    if not (math.isfinite(focal_rel) and math.isfinite(radial_px) and focal_rel >= 0
            and radial_px >= 0):
        raise ConfigError(f"calibration sigma: expected a finite relative focal and pixels "
                          f">= 0, got {calibration_sigma!r}")
    out = dict(options or {})
    out["mapping"] = {**dict(out.get("mapping") or {}),
                      **dict(zip(CALIBRATION_OPTION_KEYS, (focal_rel, radial_px), strict=True))}
    return out


def ground_truth_covariance(keyframe_sigma: tuple[float, float]) -> Array:
    """(6, 6) covariance of a dataset pose accurate to ``keyframe_sigma`` = (metres, degrees)
    per axis; ConfigError unless both are finite and >= 0."""
    t_m, r_deg = (float(v) for v in keyframe_sigma)
    if not (math.isfinite(t_m) and math.isfinite(r_deg) and t_m >= 0 and r_deg >= 0):
        raise ConfigError(f"keyframe sigma: expected finite metres and degrees >= 0, got "
                          f"{keyframe_sigma!r}")
    return pose_covariance_from_sigmas(t_m, math.radians(r_deg))


def _method_list(method: str | Sequence[str]) -> list[str]:
    methods = [method] if isinstance(method, str) else list(method)
    methods = [m.strip() for m in methods]
    if not methods or not all(methods):
        raise ConfigError(f"expected at least one non-empty method (e.g. 'gt+none'), got "
                          f"{method!r}")
    duplicates = sorted({m for m in methods if methods.count(m) > 1})
    if duplicates:
        raise ConfigError(f"method(s) {duplicates} given more than once")
    return methods


def _check_dataset(dataset: Dataset, source: LandmarkSource) -> None:
    if not dataset.query_entries:
        raise DatasetError(f"{dataset.root}: no queries to evaluate; expected a queries.txt "
                           "with ground-truth poses")
    if not dataset.map_entries:
        raise DatasetError(f"{dataset.root}: map.txt lists no keyframe")
    if source is LandmarkSource.DEPTH:
        missing = [e.image_path for e in dataset.map_entries if e.image_path not in dataset.depth]
        if missing:
            raise DatasetError(f"{dataset.root}: --landmarks depth needs a depth map for every "
                               f"map image; {len(missing)} have none (first: {missing[0]!r}) "
                               "in depth.txt")


def _make_backend(methods: list[str], options: dict[str, Any], source: LandmarkSource,
                  remote: RemoteSpec | None) -> Backend:
    if remote is None:
        return InProcessBackend(methods, options, source)
    # Imported here, not at the top: remote loads zenoh, which in-process runs do not need.
    # No cycle: remote imports .backends, never this module.
    try:
        from .remote import make_remote_backend
    except ModuleNotFoundError as exc:
        if exc.name != "reloc_service.tools.eval.remote":
            raise
        raise ConfigError("remote evaluation is not available in this installation "
                          "(reloc_service.tools.eval.remote is missing)") from None
    return make_remote_backend(remote, methods=methods, options=options, landmark_source=source)


def _timed(fn: Any) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def _build_map(backend: Backend, dataset: Dataset, source: LandmarkSource,
               progress: bool, pose_covariance: Array | None) -> float:
    """Add every map.txt keyframe (id = its row) with ``pose_covariance`` (None: none, the
    map's default); returns the time spent in the backend."""
    spent = 0.0
    entries: Iterable[tuple[int, DatasetEntry]] = enumerate(dataset.map_entries)
    if progress:
        entries = progress_bar(entries, total=len(dataset.map_entries), desc="map")
    for kf_id, entry in entries:
        image = dataset.load_image(entry)
        depth = dataset.load_depth(entry) if source.uses_depth() else None
        start = time.perf_counter()
        backend.add_keyframe(kf_id, image, dataset.camera(entry), entry.world_from_cam,
                             depth=depth, pose_covariance=pose_covariance)
        spent += time.perf_counter() - start
    return spent


def _evaluate_method(backend: Backend, dataset: Dataset, method: str,
                     progress: bool, query_camera: QueryCamera,
                     truth_covariance: Array | None = None) -> MethodResult:
    entries: Iterable[DatasetEntry] = dataset.query_entries
    if progress:
        entries = progress_bar(entries, total=len(dataset.query_entries), desc=method)
    raw = [_query(backend, dataset, entry, method, query_camera, truth_covariance)
           for entry in entries]
    records = _with_ranks(raw, dataset)
    return MethodResult(method, summarize(records), records)


def _query(backend: Backend, dataset: Dataset, entry: DatasetEntry, method: str,
           query_camera: QueryCamera, truth_covariance: Array | None = None) -> QueryRecord:
    image = dataset.load_image(entry)
    gt = np.array(entry.world_from_cam)
    camera = query_camera.claimed(dataset.camera(entry))
    start = time.perf_counter()
    result = backend.relocalize(image, camera, method=method,
                                gt_world_from_cam=gt)
    latency_ms = (time.perf_counter() - start) * 1e3
    return record_from_result(entry.image_path, result, gt, latency_ms,
                              truth_covariance=truth_covariance)


def record_from_result(image_path: str, result: RelocResult, gt_world_from_cam: Array,
                       latency_ms: float, *, truth_covariance: Array | None = None
                       ) -> QueryRecord:
    """Score one :class:`RelocResult` against the ground truth (rank left None);
    ``truth_covariance`` (6, 6): how uncertain that ground truth is (see
    :func:`.metrics.translation_mahalanobis`)."""
    est_pose = result.world_from_cam if result.ok else None
    returned = est_pose is not None
    t_err = r_err = sigma = mahalanobis = None
    est = None
    if est_pose is not None:
        dt, dr = pose_error(est_pose, gt_world_from_cam)
        t_err, r_err = dt, math.degrees(dr)
        est = pose_to_tum(est_pose).tolist()
        if result.covariance is not None:
            sigma = position_sigma_m(result.covariance)
            mahalanobis = metrics.translation_mahalanobis(est_pose, gt_world_from_cam,
                                                          result.covariance, truth_covariance)
    return QueryRecord(
        image_path=image_path, returned=returned, status=result.status.value,
        reason=result.reason, method_used=result.method, t_err_m=t_err, r_err_deg=r_err,
        latency_ms=latency_ms, confidence=float(result.confidence), inliers=int(result.inliers),
        num_matches=int(result.num_matches),
        reprojection_rms_px=(None if result.reprojection_rms_px is None
                             else float(result.reprojection_rms_px)),
        matched_keyframe_ids=[int(k) for k in result.matched_keyframe_ids], rank=None,
        gt_world_from_cam=pose_to_tum(gt_world_from_cam).tolist(), est_world_from_cam=est,
        timings_ms={k: float(v) * 1e3 for k, v in result.timings.items()},
        position_sigma_m=sigma, t_err_mahalanobis=mahalanobis)


def _with_ranks(records: list[QueryRecord], dataset: Dataset) -> list[QueryRecord]:
    """Fill ``rank`` for records that name a keyframe (keyframe id = map.txt row)."""
    n_kf = len(dataset.map_entries)
    kf_positions = np.array([e.world_from_cam[:3, 3] for e in dataset.map_entries])
    first = [r.matched_keyframe_ids[0] if r.matched_keyframe_ids else -1 for r in records]
    chosen = np.array([k if 0 <= k < n_kf else -1 for k in first], dtype=np.int64)
    query_positions = np.array([r.gt_world_from_cam[:3] for r in records])
    ranks = metrics.closest_ranks(query_positions, kf_positions, chosen)
    for record, rank, c in zip(records, ranks, chosen, strict=True):
        record.rank = int(rank) if c >= 0 else None
    return records


def summarize(records: Sequence[QueryRecord]) -> MethodSummary:
    """Aggregate per-query records (see :mod:`.metrics` for the definitions)."""
    t = np.array([math.nan if r.t_err_m is None else r.t_err_m for r in records])
    rot = np.array([math.nan if r.r_err_deg is None else r.r_err_deg for r in records])
    ok = np.array([r.returned for r in records], dtype=bool)
    latency = np.array([r.latency_ms for r in records])
    med_t, med_r = metrics.median_errors(t, rot, ok)
    ranks = [r.rank for r in records if r.rank is not None]
    mahalanobis = np.array([math.nan if r.t_err_mahalanobis is None else r.t_err_mahalanobis
                            for r in records])
    return MethodSummary(
        queries=len(records), relocalized=int(ok.sum()), recall=metrics.recalls(t, rot, ok),
        median_t_err_m=med_t, median_r_err_deg=med_r,
        mean_t_err_m=float(t[ok].mean()) if ok.any() else math.nan,
        wrong_rate=metrics.wrong_rate(t, rot, ok), off_rate=metrics.off_rate(t, rot, ok),
        not_relocalized_rate=metrics.not_relocalized_rate(ok),
        latency_p50_ms=metrics.percentile(latency, 50),
        latency_p99_ms=metrics.percentile(latency, 99),
        latency_mean_ms=float(latency.mean()) if len(latency) else math.nan,
        rank_histogram=metrics.rank_histogram(ranks),
        median_t_err_over_sigma=metrics.error_over_sigma(
            t, np.array([math.nan if r.position_sigma_m is None else r.position_sigma_m
                         for r in records]), ok),
        covariance_scale=metrics.covariance_scale(mahalanobis, ok),
        beyond_3_sigma=metrics.beyond_sigma_share(mahalanobis, ok),
        covariance_rms_scale=metrics.covariance_rms_scale(mahalanobis, ok),
        **dict(zip(("covariance_scale_low", "covariance_scale_high",
                    "covariance_scale_coverage"),
                   metrics.covariance_scale_interval(mahalanobis, ok), strict=True)))


def _map_info(backend: Backend, dataset: Dataset, source: LandmarkSource, build_s: float,
              train_s: float) -> MapInfo:
    n_kf, n_lm = backend.map_counts()
    per_keyframe = getattr(backend, "landmarks_per_keyframe", None)
    measured = getattr(backend, "keyframe_pose_sigma", None)
    errors = (backend.landmark_errors_m(dataset) if dataset.depth or dataset.truth_depth
              else None)
    median = metrics.percentile(errors, 50) if errors is not None else math.nan
    p90 = metrics.percentile(errors, 90) if errors is not None else math.nan
    return MapInfo(keyframes=n_kf, landmarks=n_lm, landmark_source=source.value,
                   build_time_s=build_s, train_time_s=train_s,
                   median_landmark_error_m=None if math.isnan(median) else median,
                   keyframe_ids=list(range(len(dataset.map_entries))),
                   keyframe_positions_world=[e.world_from_cam[:3, 3].tolist()
                                             for e in dataset.map_entries],
                   landmarks_per_keyframe=None if per_keyframe is None else per_keyframe(),
                   keyframe_pose_sigma=None if measured is None else measured(),
                   p90_landmark_error_m=None if math.isnan(p90) else p90)


def _dataset_info(dataset: Dataset, query_camera: QueryCamera) -> dict[str, Any]:
    root = Path(dataset.root).resolve()
    return {"root": str(root), "name": root.name, "map_frames": len(dataset.map_entries),
            "query_frames": len(dataset.query_entries),
            "depth_frames": len(dataset.depth),
            "cameras": {cid: cam.to_dict() for cid, cam in dataset.cameras.items()},
            "query_camera": query_camera.to_dict()}


def machine_info() -> dict[str, Any]:
    """CPU model, core count, OS, Python and library versions, so runs can be compared."""
    from importlib import metadata

    versions: dict[str, str | None] = {"reloc": __version__}
    for name in _LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"cpu": _cpu_model(), "cores": os.cpu_count(), "usable_cores": usable,
            "platform": platform.platform(), "python": platform.python_version(),
            "libraries": versions}


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
