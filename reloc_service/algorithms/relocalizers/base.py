"""The relocalizer interface (thesis chapter 4) and the shared verification.

Relocalizers answer :class:`~reloc_client.result.RelocResult`, the one result type the
service sends and the client receives (re-exported here as ``RelocResult``, ``RelocStatus``).

A wrong pose is worse than no pose for a drone: every relocalizer passes its estimate through
:func:`verify`, which answers "not relocalized" with a reason when the evidence is weak.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt
from reloc_client.protocol.geometry import pose_covariance_problem
from reloc_client.result import RelocResult, RelocStatus

from ...core.cameras import Camera
from ...core.errors import ConfigError
from ...core.features import FeatureConf
from ...core.frame import Frame, Keyframe
from ...core.map import KeyframeMap, MapState
from ...core.methods import MethodStep
from ...core.plugins import Registry
from ..pose.base import PoseEstimate, log10_false_alarms, total_covariance
from ..pose.cell_sandwich import widened
from ..pose.decision_covariance import decision_covariance
from ..pose.intrinsics import REFUSAL as INTRINSICS_REFUSAL
from ..pose.intrinsics_marginal import checked_covariance, given_calibration_covariance
from .inlier_coverage import inlier_cells, inlier_spread, on_one_plane, planar_patch_fraction

Array = npt.NDArray[np.float64]

RELOCALIZERS: Registry[Relocalizer] = Registry("relocalizer")
register = RELOCALIZERS.register


@dataclass(frozen=True)
class Prior:
    """A pose the caller believes in. With ``radius_m``, candidates are restricted to
    keyframes whose centre lies within ``radius_m`` of ``world_from_cam``'s centre; with
    ``covariance`` (6x6, twist (rho, omega), right perturbation ``world_from_cam @ exp(xi)``,
    metres and radians), the query is first tracked from it (:mod:`.tracking`)."""

    world_from_cam: Array
    radius_m: float | None = None
    covariance: Array | None = None

    def __post_init__(self) -> None:
        if self.radius_m is not None and not self.radius_m > 0:
            raise ConfigError(f"prior.radius_m: expected a positive number of metres, got "
                              f"{self.radius_m}")
        if self.covariance is not None:
            problem = pose_covariance_problem(self.covariance)
            if problem is not None:
                raise ConfigError(f"prior.covariance: expected a 6x6 pose covariance "
                                  f"(symmetric, positive semi-definite, finite; twist (rho, "
                                  f"omega), m and rad): {problem}")


@dataclass(frozen=True)
class VerifyConf:
    """Thresholds of the verification, each from statistics or geometry rather than from a
    scene: a geometric estimate passes when its consensus could not have arisen by chance
    (:func:`log10_false_alarms`), its inliers spread over the image, its residuals look like
    measurement noise rather than like random agreement, and its position is well determined.
    """

    #: Largest expected number of false alarms (a-contrario, Moisan & Stival 2004): the number
    #: of wrong poses that a consensus this large would produce by chance, per query: the 1 %
    #: wrong-pose budget of a drone.
    max_false_alarms: float = 1e-2
    #: A floor under the statistical test: with fewer inliers the residual RMS and the
    #: covariance that the other tests read are themselves unreliable (the relative standard
    #: error of a variance from 2k - 6 residuals exceeds 1/sqrt(2 * 14) ~ 19 % below k = 10).
    min_inliers: int = 10
    #: The first pose, before guided matching grew it, must have at least this many inliers:
    #: the three that determined it and as many independent ones that confirm it.
    min_unguided_inliers: int = 6
    #: Optional fixed gate on inliers / matches (0: off; the false-alarm test already weighs
    #: the inliers against the number of matches).
    min_inlier_ratio: float = 0.0
    #: Largest inlier RMS, pixels; None: derived from the estimate's inlier threshold t as
    #: t / sqrt(2), the RMS of residuals spread uniformly over the inlier disc, i.e. what
    #: agreement by chance looks like (measurement noise concentrates residuals near zero).
    max_rms_px: float | None = None
    #: Inliers must fall in at least this many cells of a ``coverage_grid`` x ``coverage_grid``
    #: grid over the image: a pose supported by one small patch (a repeated poster, a logo) is
    #: the classic perceptual-aliasing wrong pose, however small its reprojection error.
    #: Inliers that all lie on one plane must also enclose that share of the image
    #: (``min_inlier_cells / coverage_grid**2``) inside their convex hull: a small patch can
    #: touch four cells where they meet (:func:`.inlier_coverage.planar_patch_fraction`).
    min_inlier_cells: int = 4
    coverage_grid: int = 4
    #: Largest 1-sigma position uncertainty (from the covariance) accepted, metres.
    max_position_sigma_m: float = 0.2
    #: Smallest normalised cross-correlation accepted for photometric (ESM, none) estimates:
    #: aligned thumbnails of unrelated photographs reach up to ~0.8, correct alignments >= 0.95.
    min_ncc: float = 0.85
    #: Where the view cannot check the query's intrinsics (:func:`intrinsics_unchecked`) and
    #: its inliers lie on one plane, so that no view of them could (the focal and the
    #: distance trade off exactly): answer trusting the calibration (True: a relocalizer's
    #: last resort; a plane seen face on must still be answered), or refuse so that a later
    #: step of a chain, with finer features, checks them (a chain sets False on its steps
    #: but the last). Support off one plane that cannot check them is refused either way:
    #: its data are too few or too coarse, and a stale calibration would pass with the
    #: calibration's covariance.
    trust_unchecked_intrinsics: bool = True

    def __post_init__(self) -> None:
        if not 0 < self.max_false_alarms <= 1:
            raise ConfigError(f"verify.max_false_alarms must be in (0, 1], got "
                              f"{self.max_false_alarms}")
        if self.min_inliers < 4 or self.min_unguided_inliers < 4:
            raise ConfigError(f"verify.min_inliers and min_unguided_inliers must be >= 4, got "
                              f"{self.min_inliers}, {self.min_unguided_inliers}")
        if self.max_rms_px is not None and self.max_rms_px <= 0:
            raise ConfigError(f"verify.max_rms_px must be positive, got {self.max_rms_px}")


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


def log10_false_alarms_px(num_matches: int, inliers: int, threshold_px: float,
                          image_size: tuple[int, int], sample_size: int = 3, *,
                          chance_probability: float | None = None) -> float:
    """:func:`~reloc_service.algorithms.pose.base.log10_false_alarms` of a consensus within
    ``threshold_px``: a correspondence agrees by chance with probability at least
    ``pi t^2 / area`` (a wrong pose sends it to a uniformly random pixel), more where the data
    say so (``chance_probability``)."""
    width, height = image_size
    p = np.pi * threshold_px**2 / (width * height)
    p = min(max(p, chance_probability or 0.0), 1.0)
    return log10_false_alarms(num_matches, inliers, sample_size, p)


def _verify_geometric(est: PoseEstimate, conf: VerifyConf) -> tuple[bool, str, float]:
    inliers = int(est.inliers or 0)
    ratio = inliers / max(est.num_matches, 1)
    rms = est.reprojection_rms_px if est.reprojection_rms_px is not None else np.inf
    max_rms = _max_rms_px(est, conf)
    if inliers < conf.min_inliers:
        return False, f"too few inliers ({inliers} < {conf.min_inliers})", 0.0
    if est.unguided_evidence is not None and est.unguided_evidence[1] < conf.min_unguided_inliers:
        return False, (f"too few inliers before guided matching ({est.unguided_evidence[1]} "
                       f"< {conf.min_unguided_inliers})"), 0.0
    nfa = _log10_nfa(est)
    if nfa > np.log10(conf.max_false_alarms):
        matches, seed = est.unguided_evidence or (est.num_matches, inliers)
        return False, (f"consensus could be chance ({seed} of {matches} matches, "
                       f"10^{nfa:.1f} false alarms > {conf.max_false_alarms:g})"), 0.0
    if ratio < conf.min_inlier_ratio:
        return False, f"inlier ratio too low ({ratio:.2f} < {conf.min_inlier_ratio})", 0.0
    if rms > max_rms:
        return False, f"reprojection RMS too high ({rms:.2f} px > {max_rms:.2f})", 0.0
    cells = inlier_cells(est, conf.coverage_grid)
    if cells is not None and cells < conf.min_inlier_cells:
        return False, (f"inliers cover too little of the image ({cells} < {conf.min_inlier_cells} "
                       f"cells of {conf.coverage_grid}x{conf.coverage_grid})"), 0.0
    min_patch = conf.min_inlier_cells / conf.coverage_grid**2
    # Inliers spread over at least that share of the image pass the patch test whether or
    # not they lie on one plane: the plane fit is only needed below it.
    spread = inlier_spread(est)
    wide = spread is not None and spread > min_patch * (1.0 + 1e-4)  # beyond float32's error
    patch = None if wide else planar_patch_fraction(est)
    if patch is not None and patch < min_patch:
        return False, (f"inliers lie on one small planar patch ({patch:.0%} of the image < "
                       f"{min_patch:.0%}): a copy of it elsewhere would fit as well"), 0.0
    est.settle()  # the intrinsics test, left until the cheaper tests above have passed
    if est.intrinsics is not None and not est.intrinsics.passed:
        return False, est.intrinsics.reason, 0.0
    unchecked = intrinsics_unchecked(est, conf.max_position_sigma_m)
    if unchecked:
        refusal = _untrusted_calibration(est, conf)
        if refusal:
            return False, refusal, 0.0
    # Judged by the decision's covariance, not the (tighter) one the answer states: see
    # :mod:`..pose.decision_covariance`.
    sigma = position_sigma_m(decision_covariance(est, intrinsics_unchecked=unchecked))
    if sigma > conf.max_position_sigma_m:
        return False, f"position too uncertain ({sigma:.3f} m > {conf.max_position_sigma_m})", 0.0
    # Each factor saturates: many inliers, a clear majority, a small RMS.
    c_inl = 1.0 - np.exp(-(inliers - conf.min_inliers + 1) / (2 * conf.min_inliers))
    c_ratio = min(1.0, ratio / 0.45)
    c_rms = float(np.exp(-((rms / max_rms) ** 2)))
    return True, "", float(np.clip(c_inl * c_ratio * c_rms, 0.0, 1.0))


def _untrusted_calibration(est: PoseEstimate, conf: VerifyConf) -> str:
    """Why a view that cannot check the query's intrinsics is refused, or "" where the
    calibration is trusted: only support on one plane (no view of it could check them:
    the focal and the distance trade off exactly) from a relocalizer's last resort
    (``conf.trust_unchecked_intrinsics``), and only where the query claims the map's own
    calibration (the keyframes' camera): another camera's intrinsics nothing vouches for,
    and a stale one would pass with the calibration's covariance."""
    if not (conf.trust_unchecked_intrinsics and _support_on_one_plane(est)):
        return "intrinsics unchecked: the view cannot bound the focal and the distortion"
    if not est.query_camera_is_map_calibration:
        return ("intrinsics unchecked: the inliers lie on one plane, where the focal and the "
                "distance trade off, and the query's camera is not the map's calibration "
                "(expected the intrinsics of the keyframes behind the pose)")
    return ""


def note_map_calibration(estimate: PoseEstimate | None, query_camera: Camera,
                         state: MapState) -> None:
    """Set ``estimate.query_camera_is_map_calibration``: whether ``query_camera`` is exactly
    the camera of every keyframe of ``state`` behind the pose (its ``keyframe_ids``)."""
    if estimate is None:
        return
    cameras = [state.keyframes[k].camera for k in estimate.keyframe_ids if k in state.keyframes]
    estimate.query_camera_is_map_calibration = bool(cameras) and all(
        camera == query_camera for camera in cameras)


def plausible_first_pose(estimate: PoseEstimate, conf: VerifyConf) -> bool:
    """Whether ``estimate``, taken as a first pose before guided matching grows it, passes
    the tests :func:`verify` applies to that first consensus: enough inliers and a
    consensus chance would not produce."""
    inliers = int(estimate.inliers or 0)
    return (inliers >= conf.min_unguided_inliers
            and _log10_nfa(estimate) <= np.log10(conf.max_false_alarms))


def _log10_nfa(est: PoseEstimate) -> float:
    """:func:`log10_false_alarms` of ``est``; -inf (no evidence against) when it does not say
    its threshold or image size (estimates from other sources)."""
    if est.inlier_threshold_px is None or est.image_size is None:
        return -float("inf")
    matches, inliers = est.unguided_evidence or (est.num_matches, int(est.inliers or 0))
    return log10_false_alarms_px(matches, inliers, est.inlier_threshold_px, est.image_size,
                                 est.sample_size, chance_probability=est.chance_probability)


def _max_rms_px(est: PoseEstimate, conf: VerifyConf) -> float:
    if conf.max_rms_px is not None:
        return conf.max_rms_px
    if est.inlier_threshold_px is None:
        return 2.5   # an estimate that does not say its threshold: the former fixed gate
    return est.inlier_threshold_px / np.sqrt(2.0)


def _support_on_one_plane(estimate: PoseEstimate) -> bool:
    """Whether ``estimate``'s inlier points are consistent with one plane
    (:func:`on_one_plane`); False when it does not say where they are."""
    pts, sigmas = estimate.inlier_points_world, estimate.inlier_sigmas_m
    return pts is not None and sigmas is not None and len(pts) >= 4 and on_one_plane(pts, sigmas)


def position_sigma_m(covariance: Array | None) -> float:
    """1-sigma position uncertainty (metres): sqrt of the largest eigenvalue of the
    translation block; 0 when no covariance is known."""
    if covariance is None:
        return 0.0
    block = np.asarray(covariance, np.float64)[:3, :3]
    if not np.all(np.isfinite(block)):
        return float("inf")
    return math.sqrt(max(largest_eigenvalue_sym3(block.tolist()), 0.0))


def intrinsics_unchecked(estimate: PoseEstimate, max_position_sigma_m: float) -> bool:
    """Whether ``estimate``'s view cannot check the query's intrinsics: with them right, the
    covariance marginalising them would still be too wide to answer (``max_position_sigma_m``)
    because the geometry cannot bound them (a plane seen face on: the focal and the distance
    trade off; few, coarse keypoints), whatever the data happen to show. With
    ``theta ~ N(0, P)`` estimated with noise ``V``, the data's shift ``theta_hat
    theta_hat^T`` averages ``V + P``, so the marginalised ``B (theta_hat theta_hat^T + V +
    P) B^T`` averages ``B (2 V + 2 P) B^T``. ``V`` includes the map's dispersion: a map that
    bends as much cannot check the camera either. (A far solution the data cannot exclude
    is what the data show, not what the geometry allows: it widens the stated covariance.)"""
    check, trusted = estimate.intrinsics, estimate.covariance_given_intrinsics
    if check is None or trusted is None or not check.passed:
        return False
    shift = check.pose_shift
    expected = trusted + shift @ (2.0 * check.covariance + check.prior.covariance) @ shift.T
    return position_sigma_m(expected) > max_position_sigma_m


def stated_covariance(estimate: PoseEstimate, max_position_sigma_m: float) -> Array | None:
    """The covariance ``estimate`` answers with, relative to the world: its own
    (:func:`..pose.intrinsics_marginal.checked_covariance`), except where its view cannot
    check the intrinsics (:func:`intrinsics_unchecked`): the calibration's (the map's stated
    calibration accuracy alone, :func:`..pose.intrinsics_marginal.given_calibration_covariance`);
    plus the keyframe poses' errors (:func:`..pose.base.total_covariance`). A weakness: where
    the intrinsics go unchecked (a plane: :attr:`VerifyConf.trust_unchecked_intrinsics`) a
    stale calibration passes, with the calibration's covariance. What the answer states
    only: :func:`verify` judges by :func:`..pose.decision_covariance.decision_covariance`.
    Where the solver gives it, the part relative to the map is widened to its inliers'
    point-by-point spread (:func:`point_widened`) and by the noise the inlier gate cut
    (:func:`gate_widened`)."""
    if intrinsics_unchecked(estimate, max_position_sigma_m):
        own = point_widened(estimate, given_calibration_covariance(estimate))
    else:
        own = point_widened(estimate, checked_covariance(estimate))
    return total_covariance(estimate, gate_widened(estimate, own))


def gate_widened(estimate: PoseEstimate, own: Array | None) -> Array | None:
    """``own`` plus what its measurement part lacks where the inlier gate cut the keypoint
    noise's tails (:attr:`..pose.base.PoseEstimate.gate_truncation`); ``own`` where the
    solver gives none or the gate cut nothing."""
    if own is None or estimate.gate_truncation is None:
        return own
    extra = estimate.gate_truncation()
    return own if extra is None else np.asarray(own, np.float64) + extra


def point_widened(estimate: PoseEstimate, own: Array | None) -> Array | None:
    """``own`` (6, 6; ``estimate``'s covariance relative to the map, its intrinsics' part
    included) widened along the directions where the inliers' heteroskedasticity-robust
    spread (:attr:`..pose.base.PoseEstimate.point_sandwich`) exceeds it beyond chance
    (:func:`..pose.cell_sandwich.widened`, 1 % false alarm): the measurement part cannot be
    narrower than its own residuals show. ``own`` where there is no such spread."""
    if own is None or estimate.point_sandwich is None:
        return own
    sandwich = estimate.point_sandwich()
    return own if sandwich is None else widened(np.asarray(own, np.float64), *sandwich)


def largest_eigenvalue_sym3(a: list[list[float]]) -> float:
    """Largest eigenvalue of the symmetric 3x3 matrix ``a`` (its upper triangle is read), in
    closed form: the trigonometric solution of the characteristic cubic (Smith 1961), equal
    to LAPACK's ``eigvalsh`` to rounding. Python floats: a few microseconds where
    ``eigvalsh``'s call costs tens (every verified pose asks it once)."""
    a00, a01, a02, a11, a12, a22 = a[0][0], a[0][1], a[0][2], a[1][1], a[1][2], a[2][2]
    off = a01 * a01 + a02 * a02 + a12 * a12
    if off == 0.0:
        return max(a00, a11, a22)
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = math.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)
    # det(A - qI) / (2 p^3): the cosine of three times the angle of the largest root.
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
           + a02 * (a01 * a12 - b11 * a02))
    r = min(max(det / (2.0 * p * p * p), -1.0), 1.0)
    return q + 2.0 * p * math.cos(math.acos(r) / 3.0)


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
    # The verification judged the pose against the map (``estimate.covariance``); the answer
    # says how well it is known in the world, the keyframe poses' errors included.
    return RelocResult(status=RelocStatus.OK, world_from_cam=estimate.world_from_cam,
                       confidence=confidence,
                       covariance=stated_covariance(estimate, conf.max_position_sigma_m),
                       **common)


def refuses_the_query(result: RelocResult) -> bool:
    """Whether ``result`` refuses the query for what it is rather than for where it was
    looked for: its intrinsics disagree with its correspondences (:mod:`..pose.intrinsics`),
    which any other candidate, region or method would meet with the same camera. A
    relocalizer stops at such a refusal and answers it."""
    return not result.ok and result.reason.startswith(INTRINSICS_REFUSAL)


class Relocalizer(abc.ABC):
    """``add_keyframe``, ``remove_keyframe``, ``train``, ``relocalize`` (thesis chapter 4).

    A relocalizer reads keyframes and landmarks from the shared :class:`KeyframeMap`; the
    caller adds a keyframe to the map first, then tells the relocalizer (and removes it from
    the map first, then tells the relocalizer, passing the removed keyframe).
    """

    name: ClassVar[str]

    def __init__(self, kmap: KeyframeMap) -> None:
        self.map = kmap

    @classmethod
    def from_options(cls, step: MethodStep, kmap: KeyframeMap,
                     options: Mapping[str, Mapping[str, Any]]) -> Relocalizer:
        """The relocalizer the method step ``step`` names, over ``kmap``; ``options`` maps
        plugin names to their option dicts. What :func:`~.factory.create_relocalizer` calls on
        a registered class, so every registered relocalizer defines it (a chain is built by
        the factory from its steps instead)."""
        raise NotImplementedError(f"{cls.__name__} is not built from a method string")

    @property
    @abc.abstractmethod
    def method(self) -> str:
        """The method string this relocalizer answers as (e.g. ``"sbi+p3p"``)."""

    @property
    def required_features(self) -> frozenset[str]:
        """Feature kinds (``"sift"``, ``"orb"``) keyframes must carry, with landmarks."""
        return frozenset()

    @property
    def reads_keyframe_images(self) -> bool:
        """Whether it reads keyframe pixels (ferns' warps, ESM's thumbnails), so a map it
        serves keeps its keyframe images on disk. Default: no (features, landmarks and the
        small blurry images saved with the map)."""
        return False

    @property
    def reads_unmapped_keypoints(self) -> bool:
        """Whether answering a query reads map keyframes' keypoints that carry no landmark
        (5-point matching), so a map it serves keeps every keypoint on disk. Default: no
        (training may read them: an untrained method keeps them too, see ``Engine.save``)."""
        return False

    def feature_confs(self) -> dict[str, FeatureConf]:
        """The query features :meth:`relocalize` extracts, by kind, with the settings it
        extracts them with: what a chain may extract ahead for it (:data:`.chain_hooks.ON_DOUBT`) to
        the same result. Default: none."""
        return {}

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

    def save(self, directory: Path, *, centres: str = "float16"  # noqa: B027 (optional hook)
             ) -> None:
        """Write trained models into ``directory`` (created by the caller); default: none.
        ``centres``: how a vocabulary's float centres are stored, "float16" or "uint8"
        (:meth:`..place.vocabulary.VocabularyTree.to_state`)."""

    def defer_unchecked_intrinsics(self) -> None:  # noqa: B027 (optional hook)
        """Refuse, rather than trust the calibration, where a view cannot check the query's
        intrinsics (``VerifyConf.trust_unchecked_intrinsics``): a chain's steps but the last
        leave such queries to the next. Default: nothing to change."""

    def load(self, directory: Path) -> bool:
        """Restore models saved by :meth:`save`; False if there is nothing to restore.
        :meth:`Engine.load` creates the relocalizer over the loaded map and calls this without
        feeding it keyframes: whatever ``add_keyframe`` would have indexed and the model does
        not hold must be taken from the map here."""
        return False
