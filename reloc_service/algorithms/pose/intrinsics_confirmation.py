"""Whether a passing intrinsics test confirms the given camera against the error another test
estimated: its power to detect that error, and its data excluding it.

Two tests of one query's intrinsics may disagree: one refuses (its correspondences estimate a
focal ``theta_r`` off the given one), another, on other features, passes. The pass speaks for
the given camera only where the passing test would have refused had ``theta_r`` been true:
its statistic ``T^2 = theta^T W^-1 theta`` (``W``: the covariance of its model-based
component, scaled by the map's dispersion, the intrinsics' prior included) is then
Hotelling's with noncentrality ``lambda = theta_r^T W^-1 theta_r``, and it exceeds the
level's quantile of ``F(2, dof)`` with the probability of a noncentral F. Where that power is
below ``1 - missed_detection`` the pass is what the refused camera would most likely have
produced too, and cannot overrule the refusal (the criterion by which
:mod:`.intrinsics_power` bounds what a passing test lets through).

That is the precision of the data, not the power of the test as a whole, which refuses
only where its cluster-robust component (a sandwich over at most 16 grid cells) rejects too:
with few occupied cells that component sees almost no error, and a pass is judged by what the
correspondences measure.

Power is not enough: a pass whose own matches estimate nearly the refused error, let
through by the robust component, has that precision too (the validation room under a focal
30 % long: power 0.99, its unguided matches at -19 % against a refusal at -23 %, pose 1.2 m
off). It has only failed to reject the given camera, not shown the refused one wrong. So a
pass confirms the given camera only where its data also exclude the refused error
(:func:`excludes`): Hotelling's statistic of ``theta_hat - theta_r`` under the same
covariance exceeds the quantile at the test's own false-refusal rate. The two hypotheses
are treated alike: the refused camera is set aside only at the level at which the given one
would be; between the two (neither excluded) the refusal stands.

Where the passing test also tested the matches found without the pose
(:attr:`.intrinsics.IntrinsicsCheck.unguided`), its power and its exclusion are those of the
weaker of the two: matches found in windows around a pose's projections agree with its intrinsics by
construction, so the guided set's precision overstates what it could see of a wrong focal.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy import special

from .intrinsics import IntrinsicsCheck, hotelling_p_value, hotelling_t2

Array = npt.NDArray[np.float64]


def refused_theta(check: IntrinsicsCheck) -> Array:
    """(2,) the intrinsics error ``(a, b)`` the refusing component of ``check`` estimated:
    the matches found without the pose where their test refused, else the whole set's."""
    unguided = check.unguided
    if unguided is not None and unguided.p_value < check.prior.false_refusal:
        return np.asarray(unguided.theta, np.float64)
    return np.asarray(check.theta, np.float64)


def detection_power(check: IntrinsicsCheck, theta: Array) -> float:
    """Probability that ``check``'s test refuses a camera ``theta`` (2,) off the given one
    (see the module docstring), the smaller of its whole-set and unguided tests' powers."""
    checks = [check] if check.unguided is None else [check, check.unguided]
    return min(_power(c, theta) for c in checks)


def exclusion_p_value(check: IntrinsicsCheck, theta: Array) -> float:
    """P-value of "the camera is ``theta`` (2,) off the given one" on ``check``'s data: the
    model-based component's Hotelling statistic of ``theta_hat - theta`` (``F(2, dof)``,
    covariance as :func:`detection_power` takes it); the larger of its whole-set and
    unguided tests' (each must exclude ``theta``)."""
    checks = [check] if check.unguided is None else [check, check.unguided]
    return max(_exclusion_p(c, theta) for c in checks)


def excludes(check: IntrinsicsCheck, theta: Array) -> bool:
    """Whether ``check``'s data exclude a camera ``theta`` (2,) off the given one at the
    test's false-refusal rate (:func:`exclusion_p_value`)."""
    return exclusion_p_value(check, theta) < check.prior.false_refusal


def confirms(check: IntrinsicsCheck, refused: IntrinsicsCheck) -> bool:
    """Whether ``check``, a passing test, confirms the given camera against the error the
    refusing test ``refused`` estimated: it would have refused that error with probability
    at least ``1 - missed_detection``, and its data exclude it (:func:`excludes`)."""
    theta = refused_theta(refused)
    power = detection_power(check, theta)
    return (check.passed and power >= 1.0 - check.prior.missed_detection
            and excludes(check, theta))


def _power(check: IntrinsicsCheck, theta: Array) -> float:
    """Power at ``theta`` of ``check``'s model-based component: the noncentral F of
    Hotelling's statistic (``F(2, dof)``) with noncentrality ``theta^T W^-1 theta``, ``W``
    the model covariance scaled by the map's dispersion plus the calibration prior. The
    cluster-robust component (over at most 16 grid cells, ``F(2, G - 2)``) only guards the
    false-refusal rate where one region's landmarks share their errors: with a handful of
    cells its quantile is so large that it sees almost no error, and taking its power
    would leave every pass without a say (see the module docstring)."""
    return _f_power(theta, check.covariance + check.prior.covariance, check.solution.dof,
                    1.0, check.prior.false_refusal)


def _exclusion_p(check: IntrinsicsCheck, theta: Array) -> float:
    """P-value of ``theta`` as the true error on ``check``'s own estimate (1 without
    evidence: a singular covariance or no residual degrees of freedom)."""
    diff = np.asarray(check.theta, np.float64) - theta
    return hotelling_p_value(hotelling_t2(diff, check.covariance + check.prior.covariance),
                             check.solution.dof)


def _f_power(theta: Array, covariance: Array, dof: int, scale: float, level: float) -> float:
    """``P(F > f_level)`` for ``F = scale T^2 / 2`` noncentral ``F(2, dof)`` of noncentrality
    ``scale theta^T covariance^-1 theta`` (0 without residual degrees of freedom or with a
    singular covariance)."""
    lam = hotelling_t2(theta, covariance)
    if not np.isfinite(lam) or dof < 1:
        return 0.0
    limit = float(special.fdtri(2, dof, 1.0 - level))
    return float(1.0 - special.ncfdtr(2, dof, scale * max(lam, 0.0), limit))
