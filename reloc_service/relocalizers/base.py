"""The relocalizer interface (thesis chapter 4), its result, and the shared verification.

A wrong pose is worse than no pose for a drone: every relocalizer passes its estimate through
:func:`verify`, which answers "not relocalized" with a reason when the evidence is weak.
"""

from __future__ import annotations

import abc
import enum
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from ..frame import Frame, Keyframe
from ..map import KeyframeMap
from ..plugins import Registry
from ..pose.base import PoseEstimate

Array = npt.NDArray[np.float64]

RELOCALIZERS = Registry("relocalizer")
register = RELOCALIZERS.register


class RelocStatus(enum.Enum):
    """Outcome of a relocalization query."""

    OK = "ok"
    NOT_RELOCALIZED = "not_relocalized"


@dataclass(frozen=True)
class Prior:
    """A rough pose the caller believes in: candidates are restricted to keyframes whose
    centre lies within ``radius_m`` of ``world_from_cam``'s centre."""

    world_from_cam: Array
    radius_m: float


@dataclass
class RelocResult:
    """What a relocalizer answers. ``world_from_cam`` is None unless ``status`` is OK.

    ``covariance`` is 6x6 (twist (rho, omega), right perturbation, metres and radians);
    ``timings`` are seconds per stage (decode, features, place, match, solve, verify).
    """

    status: RelocStatus
    method: str
    world_from_cam: Array | None = None
    reason: str = ""
    confidence: float = 0.0
    inliers: int = 0
    num_matches: int = 0
    reprojection_rms_px: float | None = None
    covariance: Array | None = None
    matched_keyframe_ids: list[int] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    map_version: int = 0
    #: Further verified hypotheses (best first), when more than one was asked for.
    hypotheses: list[RelocResult] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status is RelocStatus.OK

    @classmethod
    def failure(cls, method: str, reason: str, **kw: Any) -> RelocResult:
        return cls(status=RelocStatus.NOT_RELOCALIZED, method=method, reason=reason, **kw)


@dataclass(frozen=True)
class VerifyConf:
    """Thresholds of the verification. Defaults are generic (not tuned to one scene): P3P
    needs a clear consensus (absolute and relative) with a small reprojection error."""

    min_inliers: int = 20
    min_inlier_ratio: float = 0.15
    max_rms_px: float = 2.5
    #: Inliers must fall in at least this many cells of a ``coverage_grid`` x ``coverage_grid``
    #: grid over the image: a pose supported by one small patch (a repeated poster, a logo) is
    #: the classic perceptual-aliasing wrong pose, however small its reprojection error.
    min_inlier_cells: int = 4
    coverage_grid: int = 4
    #: Largest 1-sigma position uncertainty (from the covariance) accepted, metres.
    max_position_sigma_m: float = 0.2
    #: Smallest normalised cross-correlation accepted for photometric (ESM, none) estimates:
    #: aligned thumbnails of unrelated photographs reach up to ~0.8, correct alignments >= 0.95.
    min_ncc: float = 0.85


def verify(estimate: PoseEstimate | None, conf: VerifyConf) -> tuple[bool, str, float]:
    """Judge ``estimate``: (accepted, reason if refused, confidence in [0, 1])."""
    if estimate is None:
        return False, "no pose hypothesis", 0.0
    if not np.all(np.isfinite(estimate.world_from_cam)):
        return False, "non-finite pose", 0.0
    if estimate.inliers is not None:
        return _verify_geometric(estimate, conf)
    if estimate.ncc is not None:
        ok = estimate.ncc >= conf.min_ncc
        confidence = float(np.clip((estimate.ncc - conf.min_ncc) / (1 - conf.min_ncc + 1e-9), 0, 1))
        reason = "" if ok else f"image alignment too weak (ncc {estimate.ncc:.2f} < {conf.min_ncc})"
        return ok, reason, confidence if ok else 0.0
    return False, "estimate carries no evidence to verify", 0.0


def _verify_geometric(est: PoseEstimate, conf: VerifyConf) -> tuple[bool, str, float]:
    inliers = int(est.inliers or 0)
    ratio = inliers / max(est.num_matches, 1)
    rms = est.reprojection_rms_px if est.reprojection_rms_px is not None else np.inf
    if inliers < conf.min_inliers:
        return False, f"too few inliers ({inliers} < {conf.min_inliers})", 0.0
    if ratio < conf.min_inlier_ratio:
        return False, f"inlier ratio too low ({ratio:.2f} < {conf.min_inlier_ratio})", 0.0
    if rms > conf.max_rms_px:
        return False, f"reprojection RMS too high ({rms:.2f} px > {conf.max_rms_px})", 0.0
    cells = inlier_cells(est, conf.coverage_grid)
    if cells is not None and cells < conf.min_inlier_cells:
        return False, (f"inliers cover too little of the image ({cells} < {conf.min_inlier_cells} "
                       f"cells of {conf.coverage_grid}x{conf.coverage_grid})"), 0.0
    sigma = position_sigma_m(est.covariance)
    if sigma > conf.max_position_sigma_m:
        return False, f"position too uncertain ({sigma:.3f} m > {conf.max_position_sigma_m})", 0.0
    # Each factor saturates: many inliers, a clear majority, a small RMS.
    c_inl = 1.0 - np.exp(-(inliers - conf.min_inliers + 1) / conf.min_inliers)
    c_ratio = min(1.0, ratio / (3 * conf.min_inlier_ratio))
    c_rms = float(np.exp(-((rms / conf.max_rms_px) ** 2)))
    return True, "", float(np.clip(c_inl * c_ratio * c_rms, 0.0, 1.0))


def inlier_cells(estimate: PoseEstimate, grid: int) -> int | None:
    """Number of cells of a ``grid`` x ``grid`` partition of the image holding an inlier; None
    when the estimate does not say where its inliers are."""
    if estimate.inlier_px is None or estimate.image_size is None or len(estimate.inlier_px) == 0:
        return None
    width, height = estimate.image_size
    col = np.clip((estimate.inlier_px[:, 0] + 0.5) * grid // width, 0, grid - 1).astype(int)
    row = np.clip((estimate.inlier_px[:, 1] + 0.5) * grid // height, 0, grid - 1).astype(int)
    return len(np.unique(row * grid + col))


def position_sigma_m(covariance: Array | None) -> float:
    """1-sigma position uncertainty (metres): sqrt of the largest eigenvalue of the
    translation block; 0 when no covariance is known."""
    if covariance is None:
        return 0.0
    block = np.asarray(covariance)[:3, :3]
    if not np.all(np.isfinite(block)):
        return float("inf")
    return float(np.sqrt(max(np.linalg.eigvalsh(block).max(), 0.0)))


def result_from_estimate(estimate: PoseEstimate | None, conf: VerifyConf, *, method: str,
                         map_version: int, timings: dict[str, float]) -> RelocResult:
    """Verify ``estimate`` and wrap it as a :class:`RelocResult` (shared by every relocalizer)."""
    ok, reason, confidence = verify(estimate, conf)
    common: dict[str, Any] = dict(method=method, map_version=map_version, timings=timings)
    if estimate is not None:
        common.update(inliers=int(estimate.inliers or 0), num_matches=estimate.num_matches,
                      reprojection_rms_px=estimate.reprojection_rms_px,
                      matched_keyframe_ids=list(estimate.keyframe_ids))
    if not ok:
        return RelocResult.failure(reason=reason, **common)
    assert estimate is not None
    return RelocResult(status=RelocStatus.OK, world_from_cam=estimate.world_from_cam,
                       confidence=confidence, covariance=estimate.covariance, **common)


class Relocalizer(abc.ABC):
    """``add_keyframe``, ``remove_keyframe``, ``train``, ``relocalize`` (thesis chapter 4).

    A relocalizer reads keyframes and landmarks from the shared :class:`KeyframeMap`; the
    caller adds a keyframe to the map first, then tells the relocalizer (and removes it from
    the map first, then tells the relocalizer, passing the removed keyframe).
    """

    name: ClassVar[str]

    def __init__(self, kmap: KeyframeMap) -> None:
        self.map = kmap

    @property
    @abc.abstractmethod
    def method(self) -> str:
        """The method string this relocalizer answers as (e.g. ``"sbi+p3p"``)."""

    @property
    def required_features(self) -> frozenset[str]:
        """Feature kinds (``"sift"``, ``"orb"``) keyframes must carry, with landmarks."""
        return frozenset()

    @abc.abstractmethod
    def add_keyframe(self, keyframe: Keyframe) -> None:
        """Learn ``keyframe`` (already in the map)."""

    @abc.abstractmethod
    def remove_keyframe(self, keyframe: Keyframe) -> None:
        """Forget ``keyframe`` (already removed from the map)."""

    def train(self, *, progress: bool = False) -> None:  # noqa: B027 (optional hook)
        """(Re)build models from the whole map; default: nothing to train."""

    @property
    def trained(self) -> bool:
        return True

    @abc.abstractmethod
    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        """The query's ``world_from_cam``, verified, or NOT_RELOCALIZED with a reason."""

    def save(self, directory: Path) -> None:  # noqa: B027 (optional hook)
        """Write trained models into ``directory`` (created by the caller); default: none."""

    def load(self, directory: Path) -> bool:
        """Restore models saved by :meth:`save`; False if there is nothing to restore."""
        return False
