"""What the intrinsics test misses, and what that does to a pose that passes it.

The test (:mod:`.intrinsics`) refuses where ``T^2 = theta^T W^-1 theta`` exceeds the
chi-square(2) quantile ``c`` at its false-refusal rate. A query whose intrinsics are really
``theta`` off gives ``T^2`` distributed as a noncentral chi-square with 2 degrees of freedom
and noncentrality ``theta^T W^-1 theta``: the test misses it with probability
``ncx2.cdf(c, 2, lambda)``. Every error missed with a probability above ``beta`` (the
missed-detection rate) thus lies inside the ellipse ``theta^T W^-1 theta <= lambda_beta``
(:func:`missed_noncentrality`), and its pose shift ``B theta`` inside the 3-sigma ellipse of
``B (lambda_beta / 9) W B^T``: the answers given under such a stale calibration are exactly
the draws that fell inside the test's acceptance region, so their estimate ``theta_hat`` is
biased towards zero and the expected squared shift ``B (theta_hat theta_hat^T + W) B^T``
that holds over all queries does not hold over the answered ones. This is the protection
level of satellite navigation's integrity monitoring (a minimal detectable bias times its
effect on the position, Brown 1996), here for the focal and the radial distortion.

Where the data cannot exclude a camera that moves the pose beyond 3 sigma of the covariance
it states trusting the calibration (:func:`unresolved`), the test lacks the power to vouch
for the pose, and the linear shift ``B theta`` is all the covariance knows of what such a
camera does: a step of a chain followed by one with other, finer features asks it too
(:meth:`..relocalizers.chain.ChainRelocalizer._underpowered`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from ...core import distributions as stats
from .base import PoseEstimate, total_covariance
from .intrinsics import IntrinsicsCheck, hotelling_p_value, hotelling_t2

Array = npt.NDArray[np.float64]

#: Mahalanobis radius within which a pose shift counts as covered by a covariance (3 sigma).
COVERED_SIGMAS = 3.0


@functools.lru_cache(maxsize=64)
def missed_noncentrality(false_refusal: float, missed_detection: float, dof: int = 2) -> float:
    """The noncentrality ``lambda`` at which a chi-square test with ``dof`` degrees of freedom
    at level ``false_refusal`` misses an error with probability ``missed_detection``
    (``ncx2.cdf(chi2.isf(false_refusal), dof, lambda) = missed_detection``); 0 where even no
    error is missed that rarely (``missed_detection >= 1 - false_refusal``)."""
    limit = float(stats.chi2.isf(false_refusal, dof))
    if missed_detection >= 1.0 - false_refusal:
        return 0.0

    def excess(lam: float) -> float:
        return float(stats.ncx2.cdf(limit, dof, lam)) - missed_detection

    return _decreasing_root(excess, 1e-9, 1e4, xtol=1e-9)


def _decreasing_root(f: Callable[[float], float], lo: float, hi: float, *,
                     xtol: float) -> float:
    """The root of ``f``, decreasing on ``[lo, hi]`` (``f(lo) >= 0 >= f(hi)``), within
    ``xtol``: bisection, 44 calls over ``[1e-9, 1e4]`` (``ncx2.cdf`` decreases with the
    noncentrality). Not ``scipy.optimize.brentq``: importing ``scipy.optimize`` took a
    quarter of a second of a service's start-up, for a root found once per rate pair."""
    f_lo, f_hi = f(lo), f(hi)
    if f_lo < 0 or f_hi > 0:
        raise ValueError(f"expected a sign change on [{lo}, {hi}], got f = {f_lo}, {f_hi}")
    while hi - lo > xtol:
        mid = 0.5 * (lo + hi)
        if f(mid) > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def governing_covariance(check: IntrinsicsCheck) -> Array:
    """(2, 2) ``W``: the covariance (the intrinsics' prior included) of the test's component
    that let ``check`` pass, the one with the larger p-value (the test refuses only where
    both the model-based and the cluster-robust components reject, so the weaker of the two
    decides what passes)."""
    chosen = check.solution
    model = check.covariance + check.prior.covariance
    if chosen.robust_covariance is None:
        return model
    robust = chosen.robust_covariance + check.prior.covariance
    g = chosen.clusters
    p_model = _p_value(chosen.theta, model, chosen.dof, 1.0)
    p_robust = _p_value(chosen.theta, robust, g - 2, (g - 2) / (g - 1))
    return robust if p_robust > p_model else model


def blind_spot_factor(check: IntrinsicsCheck) -> float:
    """``lambda_beta / 9`` (at least 1): how much the governing covariance is widened so that
    every intrinsics error the test misses with probability above its missed-detection rate
    lies within 3 of its sigmas."""
    prior = check.prior
    lam = missed_noncentrality(prior.false_refusal, prior.missed_detection)
    return max(1.0, lam / COVERED_SIGMAS**2)


def undetected_covariance(check: IntrinsicsCheck) -> Array:
    """(2, 2) the covariance whose 3-sigma ellipse holds every intrinsics error ``check``'s
    test misses with probability above ``prior.missed_detection``: ``(lambda_beta / 9) W``."""
    return blind_spot_factor(check) * governing_covariance(check)


def unresolved(check: IntrinsicsCheck, trusted_covariance: Array) -> bool:
    """Whether the correspondences cannot tell the given camera from one that moves the pose
    beyond 3 sigma of ``trusted_covariance`` (6, 6: the pose's covariance with the
    calibration trusted within its prior): the farthest solution the likelihood-ratio test
    cannot exclude (:attr:`.intrinsics.IntrinsicsCheck.unexcluded_twist`) lies beyond 3 of
    its sigmas in position."""
    far = check.unexcluded_twist[:3]
    rest = np.asarray(trusted_covariance, np.float64)[:3, :3]
    try:
        squared = float(far @ np.linalg.solve(rest, far))
    except np.linalg.LinAlgError:
        return True
    return not squared <= COVERED_SIGMAS**2


def estimate_underpowered(estimate: PoseEstimate) -> bool:
    """Whether ``estimate``'s intrinsics test, where it passed, is too weak to vouch for the
    pose: the data cannot exclude a camera that moves it beyond 3 sigma of the covariance
    it states trusting the calibration (:func:`unresolved`, keyframe poses' errors
    included). False where nothing passed to judge."""
    check, trusted = estimate.intrinsics, estimate.covariance_given_intrinsics
    if check is None or trusted is None or not check.passed:
        return False
    total = total_covariance(estimate, trusted)
    return total is not None and unresolved(check, total)


def _p_value(theta: Array, covariance: Array, dof: int, scale: float) -> float:
    """P-value of ``theta`` under ``covariance`` as the test computes it (Hotelling's ``F(2,
    dof)`` of ``scale T^2 / 2``); 1 without evidence."""
    return hotelling_p_value(scale * hotelling_t2(theta, covariance), dof)
