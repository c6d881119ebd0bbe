"""The focal starts of the intrinsics test a pose prior leaves open.

The intrinsics test (:func:`.intrinsics.check_intrinsics`) starts its joint estimate of the
pose and the focal from the given camera and from focal scales 0.66 to 1.52, because a wrong
focal ``1 + e`` is absorbed by a camera moved along its optical axis by about ``e`` times the
scene depth: the pose at the given focal then lies that far from the true one. A pose prior
whose gate the answer must meet bounds that move: an answer more than
``sqrt(chi2_6(p))`` standard deviations from the prior along the optical axis lies outside
the 6-dof gate whatever its other components (the Mahalanobis distance of a shift along one
axis is at least the shift over that axis's marginal sigma). So a focal error whose shift
``|e| depth`` exceeds that reach is excluded by the prior, and a start whose basin (the
focals within half a step of the geometric series, which is how far Gauss-Newton reaches
from it) holds no admissible focal finds nothing the gate would let through."""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from ...core.geometry import invert, transform_points
from .base import PoseEstimate
from .intrinsics import FOCAL_STARTS, IntrinsicsCheck

Array = npt.NDArray[np.float64]


def focal_reach(axis_variance_m2: float, depth_m: float, gate_chi2: float) -> float:
    """The largest relative focal error ``|e|`` whose shift along the optical axis
    (``|e| depth_m``) stays within ``sqrt(gate_chi2)`` of the axis sigma
    ``sqrt(axis_variance_m2)``; inf where the depth is unknown."""
    if not (np.isfinite(depth_m) and depth_m > 0 and np.isfinite(axis_variance_m2)):
        return float("inf")
    return float(np.sqrt(gate_chi2 * max(axis_variance_m2, 0.0)) / depth_m)


def focal_starts_within(reach: float, starts: tuple[float, ...] = FOCAL_STARTS
                        ) -> tuple[float, ...]:
    """The ``starts`` (focal scales of a geometric series through the given focal, 1) whose
    basin, half a step of the series either side in ratio, meets the admissible focals
    ``[1 - reach, 1 + reach]``."""
    if not np.isfinite(reach) or not starts:
        return tuple(starts)
    ordered = sorted({*starts, 1.0})
    half_step = float(np.sqrt(max(b / a for a, b in zip(ordered, ordered[1:], strict=False))))
    return tuple(f for f in starts
                 if f / half_step <= 1.0 + reach and f * half_step >= 1.0 - reach)


def axis_variance(prior_covariance: Array, own_covariance: Array | None) -> float:
    """(m^2) the variance along the camera's optical axis (twist component ``rho_z``, the
    third: the translation of a right perturbation is in the camera frame) of the gate's
    covariance: the prior's plus the answer's own."""
    total = float(np.asarray(prior_covariance, np.float64)[2, 2])
    if own_covariance is not None:
        total += float(np.asarray(own_covariance, np.float64)[2, 2])
    return total


def limit_focal_starts(est: PoseEstimate, prior_covariance: Array, inliers_world: Array,
                       gate_chi2: float) -> None:
    """Start ``est``'s intrinsics test only from the focals the prior's gate (``gate_chi2``,
    6 degrees of freedom) leaves open: a focal error the gate excludes needs no search.
    The reach is judged at the median depth of the (N, 3) ``inliers_world``."""
    if est.intrinsics_test is None or len(inliers_world) == 0:
        return
    depth = float(np.median(transform_points(invert(est.world_from_cam), inliers_world)[:, 2]))
    reach = focal_reach(axis_variance(prior_covariance, est.covariance), depth, gate_chi2)
    # The test is pnp's, which takes its focal starts by keyword.
    test: Callable[..., IntrinsicsCheck | None] = est.intrinsics_test
    est.intrinsics_test = functools.partial(test, focal_starts=focal_starts_within(reach))
