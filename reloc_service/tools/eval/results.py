"""What ``reloc eval`` measured, as records: one per query (:class:`QueryRecord`), a summary and
the records per method, the map, and the whole run (:class:`EvalResult`), with the versioned
JSON of docs/eval_schema.md (:meth:`EvalResult.to_dict`, :meth:`EvalResult.from_dict`)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...core.errors import ConfigError

#: Version of the dictionary written by :meth:`EvalResult.to_dict` (docs/eval_schema.md).
SCHEMA_VERSION = 1


@dataclass
class QueryRecord:
    """One query's outcome: a :class:`RelocResult` as the versioned JSON record of
    docs/eval_schema.md, plus what the evaluation adds (errors, latency, ground truth, rank).
    Built from a result only by :func:`record_from_result` (and from JSON by
    :meth:`EvalResult.from_dict`); it keeps the pose as the 7 numbers the JSON holds rather
    than the result's matrix, so a record read back from its JSON equals the one written.

    Errors are None when no pose was returned; ``rank`` is the rank k (1 = closest) of the
    first matched keyframe among the keyframes ordered by distance to the query's
    ground-truth centre (thesis figure 3.2), None when the result names no keyframe.
    Poses are ``world_from_cam`` as ``[tx, ty, tz, qx, qy, qz, qw]``."""

    image_path: str
    returned: bool
    status: str
    reason: str
    method_used: str
    t_err_m: float | None
    r_err_deg: float | None
    latency_ms: float
    confidence: float
    inliers: int
    num_matches: int
    reprojection_rms_px: float | None
    matched_keyframe_ids: list[int]
    rank: int | None
    gt_world_from_cam: list[float]
    est_world_from_cam: list[float] | None
    timings_ms: dict[str, float] = field(default_factory=dict)
    #: The result's own 1-sigma position uncertainty (:func:`position_sigma_m` of its
    #: covariance), None when no pose or no covariance was returned.
    position_sigma_m: float | None = None
    #: Length of the translation error under the result's covariance
    #: (:func:`.metrics.translation_mahalanobis`), None when no pose or no covariance.
    t_err_mahalanobis: float | None = None


@dataclass
class MethodSummary:
    """Aggregates of one method over all queries (rates are fractions of all queries)."""

    queries: int
    relocalized: int
    recall: dict[str, float]
    median_t_err_m: float
    median_r_err_deg: float
    mean_t_err_m: float
    wrong_rate: float
    not_relocalized_rate: float
    latency_p50_ms: float
    latency_p99_ms: float
    latency_mean_ms: float
    rank_histogram: dict[int, int]
    #: Median of translation error / stated position sigma over returned poses with a
    #: covariance (:func:`.metrics.error_over_sigma`): about 1 when the covariance is honest.
    median_t_err_over_sigma: float = math.nan
    #: Median Mahalanobis length of the translation errors over its Gaussian value
    #: (:func:`.metrics.covariance_scale`): 1 when the covariance is honest, 2 when its
    #: sigmas are half what the errors show.
    covariance_scale: float = math.nan
    #: A distribution-free confidence interval of ``covariance_scale`` and the probability
    #: it holds the true scale (:func:`.metrics.covariance_scale_interval`; 95 % or more
    #: from 6 answers on, less below; NaN with fewer than two answers).
    covariance_scale_low: float = math.nan
    covariance_scale_high: float = math.nan
    covariance_scale_coverage: float = math.nan
    #: Fraction of all queries answered beyond 25 cm / 10 deg (:func:`.metrics.off_rate`).
    off_rate: float = math.nan
    #: Share of the answers with a covariance more than 3 sigmas off
    #: (:func:`.metrics.beyond_sigma_share`; 2.9 % for honest Gaussian errors).
    beyond_3_sigma: float = math.nan
    #: The scale the stated sigmas need for the errors' second moment
    #: (:func:`.metrics.covariance_rms_scale`): what a filter fusing the answers needs.
    covariance_rms_scale: float = math.nan


@dataclass
class MethodResult:
    """A method's per-query records and their summary."""

    method: str
    summary: MethodSummary
    queries: list[QueryRecord]


@dataclass
class MapInfo:
    """The map every method was evaluated on, and what it cost to build and train."""

    keyframes: int
    landmarks: int
    landmark_source: str
    build_time_s: float
    train_time_s: float
    median_landmark_error_m: float | None
    keyframe_ids: list[int]
    keyframe_positions_world: list[list[float]]
    #: Landmarks observed by each keyframe (keyframe_ids order); None when the backend cannot
    #: tell (remote maps).
    landmarks_per_keyframe: list[int] | None = None
    #: The keyframe pose uncertainty the map measured of itself and states for keyframes put
    #: without a covariance (:meth:`~reloc_service.algorithms.pose.keyframe_disagreement.
    #: KeyframePoseSigma.as_dict`); None when it measured none (stated sigmas, remote maps).
    keyframe_pose_sigma: dict[str, Any] | None = None
    #: 90th percentile of the landmarks' distances to their ground truth (None as for the
    #: median): a map can be exact in its median and metres off in a tenth of its points.
    p90_landmark_error_m: float | None = None


@dataclass
class EvalResult:
    """Everything one ``reloc eval`` run measured; :meth:`to_dict` is the JSON schema."""

    dataset: dict[str, Any]
    map: MapInfo
    methods: list[MethodResult]
    machine: dict[str, Any]
    backend: str
    options: dict[str, Any]
    created_utc: str
    schema_version: int = SCHEMA_VERSION
    #: (metres, degrees): the 1-sigma accuracy per axis of the dataset's poses
    #: (``--keyframe-sigma``): the map's keyframes were put with that pose covariance and
    #: every query's ground truth was taken as that uncertain (0, 0: both exact).
    ground_truth_sigma: tuple[float, float] = (0.0, 0.0)

    def method(self, name: str) -> MethodResult:
        """The result of method ``name``; KeyError naming the evaluated ones otherwise."""
        for m in self.methods:
            if m.method == name:
                return m
        raise KeyError(f"method {name!r} was not evaluated; evaluated: "
                       f"{[m.method for m in self.methods]}")

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (NaN and infinities become None), schema ``schema_version``."""
        d = asdict(self)
        d = {"schema_version": d.pop("schema_version"), **d}
        for m in d["methods"]:
            m["summary"]["rank_histogram"] = {str(k): v for k, v in
                                              m["summary"]["rank_histogram"].items()}
        return json_safe(d)

    def write_json(self, path: str | Path) -> Path:
        """Write :meth:`to_dict` to ``path`` (parents created); returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n",
                        encoding="utf-8")
        return path

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EvalResult:
        """Rebuild a result from :meth:`to_dict` output (None numbers read back as NaN)."""
        version = d.get("schema_version")
        if version != SCHEMA_VERSION:
            raise ConfigError(f"eval result schema_version {version!r}; this reloc reads "
                              f"version {SCHEMA_VERSION}")
        methods = [MethodResult(m["method"], _summary_from_dict(m["summary"]),
                                [QueryRecord(**q) for q in m["queries"]]) for m in d["methods"]]
        sigma = d.get("ground_truth_sigma") or (0.0, 0.0)
        return cls(dataset=dict(d["dataset"]), map=MapInfo(**d["map"]), methods=methods,
                   machine=dict(d["machine"]), backend=d["backend"], options=dict(d["options"]),
                   created_utc=d["created_utc"], schema_version=version,
                   ground_truth_sigma=(float(sigma[0]), float(sigma[1])))


def _summary_from_dict(s: Mapping[str, Any]) -> MethodSummary:
    s = {k: (math.nan if v is None else v) for k, v in s.items()}
    s["recall"] = {k: (math.nan if v is None else v) for k, v in s["recall"].items()}
    s["rank_histogram"] = {int(k): int(v) for k, v in s["rank_histogram"].items()}
    return MethodSummary(**s)


def json_safe(value: Any) -> Any:
    """``value`` with NumPy scalars and arrays as Python numbers and lists, NaN and infinities
    as None (strict JSON)."""
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
