"""The robust absolute-pose settings every P3P user shares (:mod:`.pnp`, the P3P pose finder,
ferns, tracking): RANSAC, refinement, keypoint noise, the intrinsics test's rates and the
stated covariance's widenings, checked when made."""

from __future__ import annotations

from dataclasses import dataclass

from ...core.errors import ConfigError
from .intrinsics import IntrinsicsPrior


@dataclass(frozen=True)
class PnPConf:
    """Robust absolute-pose settings shared by every P3P user (this module, ferns)."""

    #: RANSAC inlier threshold and final inlier gate, pixels.
    max_reproj_error_px: float = 5.0
    min_iterations: int = 50
    max_iterations: int = 10000
    success_prob: float = 0.9999
    seed: int = 0
    #: Gauss-Newton steps through the real (distorted) camera model after PoseLib.
    refine_iterations: int = 1
    #: Floor of the residual standard deviation used for the covariance, pixels (keypoints
    #: are not more precise than this, however well a few of them happen to fit).
    min_sigma_px: float = 0.25
    #: Localisation noise of a query keypoint, pixels: with a landmark's depth uncertainty
    #: projected into the query (``s`` pixels), its residual weighs ``1 / (1 + (s / this)^2)``
    #: in the refinement and the covariance.
    keypoint_sigma_px: float = 1.0
    #: Test the query's intrinsics on the pose's correspondences (:mod:`.intrinsics`): a
    #: focal scale and a radial distortion term estimated with the pose, the given camera
    #: refused at this false-refusal rate (the share of correctly calibrated queries refused).
    #: 0: no test.
    intrinsics_false_refusal: float = 1e-3
    #: A correct calibration's 1-sigma uncertainty: of the focal, relative, and of the
    #: distortion, as the pixels it moves the image's farthest corner. The test allows it; a
    #: pose that passes carries it in its covariance.
    focal_sigma_rel: float = 0.005
    radial_sigma_px: float = 2.0
    #: The share of stale calibrations a passing pose's covariance may fail to cover: every
    #: intrinsics error the test misses more often than this moves the pose within 3 of its
    #: stated sigmas (:mod:`.intrinsics_power`).
    intrinsics_missed_detection: float = 0.5
    #: State the map's dispersion robust to mis-associated landmarks (each keyframe's
    #: held-out statistic on its chi-square gate's inliers where the gate left out more than
    #: honest residuals explain, :mod:`.map_consistency`) in the answer's covariance; the
    #: decisions keep the plain one either way. Alone it brings repeated into the cov-scale
    #: band (0.60 -> 0.79) but makes degraded sets more confident (room-hard 1.27 -> 1.45),
    #: which ``stated_cell_sandwich`` makes up for.
    robust_stated_dispersion: bool = True
    #: Widen the measurement part of the answer's covariance to the cluster-robust spread
    #: its inliers show over the coverage grid's cells, where it exceeds the model's at a 1 %
    #: false-alarm rate (:mod:`.cell_sandwich`); the decisions keep the model covariance.
    stated_cell_sandwich: bool = True
    #: Widen the answer's covariance to the spread its inliers show one by one (White's
    #: sandwich), where beyond chance at 1 % (:func:`.cell_sandwich.point_sandwich`): noise
    #: growing with leverage or along one direction (blur). Decisions keep the model's.
    stated_point_sandwich: bool = True
    #: Widen the measurement part of the answer's covariance to the keypoint noise its
    #: inliers show once the inlier gate's truncation is undone (:mod:`.gate_truncation`):
    #: noise comparable to ``max_reproj_error_px`` (blur) loses its tails to the gate and the
    #: residuals understate it. Decisions keep the model covariance.
    stated_gate_truncation: bool = True
    #: Judge the intrinsics test on a grown pose's unguided matches with the intra-cell
    #: correlation the map's keyframes show (:mod:`.cell_correlation`, its upper 95 % bound)
    #: as a design effect on the model covariance, instead of the cluster-robust reference
    #: over the 3-5 cells those matches occupy, which has almost no degrees of freedom.
    unguided_cell_correlation: bool = False
    #: State a grown pose's covariance, where the query does not claim the map's calibration,
    #: with the intrinsics moment its unguided matches cannot exclude where it exceeds the
    #: whole inlier set's (:mod:`.intrinsics_envelope`): guided matches agree with the claimed
    #: focal by construction, so the whole set's estimate may be bent towards it. Decisions
    #: keep their covariance, so no answer changes. On: with focals claimed 1.05, 1.15 and
    #: 1.3 times the camera's on tum, 7scenes, room-hard, repeated-hard and val
    #: repeated-hard_s2, answers beyond 3 sigma 25 -> 10 of 130, none new; it is
    #: conservative there (x1.05 room-hard cov scale 1.00 -> 0.55). Queries claiming the
    #: map's calibration are untouched (the 18 default sets per query identical).
    stated_unguided_intrinsics: bool = True

    def __post_init__(self) -> None:
        if self.max_reproj_error_px <= 0:
            raise ConfigError(f"max_reproj_error_px must be positive, "
                              f"got {self.max_reproj_error_px}")
        if not 0 < self.min_iterations <= self.max_iterations:
            raise ConfigError(f"expected 0 < min_iterations <= max_iterations, got "
                              f"{self.min_iterations}, {self.max_iterations}")
        if not 0 < self.success_prob < 1:
            raise ConfigError(f"success_prob must be in (0, 1), got {self.success_prob}")
        if self.keypoint_sigma_px <= 0:
            raise ConfigError(f"keypoint_sigma_px must be positive, got {self.keypoint_sigma_px}")
        if self.refine_iterations < 0 or self.min_sigma_px < 0:
            raise ConfigError("refine_iterations and min_sigma_px must be >= 0")
        if not 0 <= self.intrinsics_false_refusal < 1:
            raise ConfigError(f"intrinsics_false_refusal must be in [0, 1), got "
                              f"{self.intrinsics_false_refusal}")
        if not 0 < self.intrinsics_missed_detection < 1:
            raise ConfigError(f"intrinsics_missed_detection must be in (0, 1), got "
                              f"{self.intrinsics_missed_detection}")
        if self.focal_sigma_rel <= 0 or self.radial_sigma_px <= 0:
            raise ConfigError(f"focal_sigma_rel and radial_sigma_px must be positive, got "
                              f"{self.focal_sigma_rel}, {self.radial_sigma_px}")

    @property
    def intrinsics_prior(self) -> IntrinsicsPrior:
        """The calibration uncertainty and false-refusal rate :mod:`.intrinsics` tests with."""
        return IntrinsicsPrior(self.focal_sigma_rel, self.radial_sigma_px,
                               self.intrinsics_false_refusal, self.intrinsics_missed_detection)
