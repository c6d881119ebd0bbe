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
(:attr:`.intrinsics.IntrinsicsCheck.unguided`), matches found in windows around a pose's
projections may agree with its intrinsics by construction, so the guided set's precision may
overstate what it could see of a wrong focal. Whether they did is itself testable (Hausman
1978): the unguided matches are a subset of the whole set, so under "guided matching added
no bias" the whole set's estimate is the efficient one and the difference of the two
estimates has covariance ``V_u - V_w`` (the unguided one's minus the whole set's); its
statistic is chi-square with the rank of that difference as degrees of freedom
(:func:`guided_bias_p_value`). Where it rejects at :data:`GUIDED_BIAS_LEVEL`, the power and
the exclusion are those of the weaker of the two sets, as the guided matches cannot be
trusted; where it does not, the whole set's (its unguided part has seen nothing against
it). Unguided matches too few to see the refused error then no longer veto a pass that
sees it (room-hard query 38 with the right camera: bow+p3p's 20 unguided inliers estimating
+52 +- 230 %, power 0, against the whole set's -3.6 +- 1.3 %).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy import special

from ...core import distributions as stats
from .intrinsics import IntrinsicsCheck, hotelling_p_value, hotelling_t2

Array = npt.NDArray[np.float64]

#: Level of the test that guided matching bent the whole set's estimate (the rate at which
#: an unbiased guided set is distrusted): a false alarm only returns the judgement to the
#: weaker of the guided and unguided sets (the rule without this test), a miss lets a bent
#: estimate confirm the given camera, so the level is the conventional 5 %, not the
#: intrinsics test's false-refusal rate.
GUIDED_BIAS_LEVEL = 0.05

#: Eigenvalues of ``V_u - V_w`` below this share of its largest are taken as zero (a
#: direction the unguided matches know no worse than the whole set: no test along it).
_RANK_TOLERANCE = 1e-9


def refused_theta(check: IntrinsicsCheck) -> Array:
    """(2,) the intrinsics error ``(a, b)`` the refusing component of ``check`` estimated:
    the matches found without the pose where their test refused, else the whole set's."""
    unguided = check.unguided
    if unguided is not None and unguided.p_value < check.prior.false_refusal:
        return np.asarray(unguided.theta, np.float64)
    return np.asarray(check.theta, np.float64)


def guided_bias_p_value(check: IntrinsicsCheck) -> float:
    """P-value of "guided matching did not bend ``check``'s estimate": Hausman's statistic
    ``d^T (V_u - V_w)^+ d`` of the difference ``d`` of the unguided and whole-set estimates
    (each covariance the model's, scaled by the map's dispersion), chi-square with the
    rank of ``V_u - V_w`` degrees of freedom (its generalised inverse over the positive
    eigenvalues). 1 without an unguided test; 0 where the unguided estimate is no less
    precise than the whole set's in any direction yet differs (nothing to compare against
    the difference but zero)."""
    unguided = check.unguided
    if unguided is None:
        return 1.0
    diff = np.asarray(unguided.theta, np.float64) - np.asarray(check.theta, np.float64)
    gap = unguided.covariance - check.covariance
    values, vectors = np.linalg.eigh(0.5 * (gap + gap.T))
    if not np.all(np.isfinite(values)):
        return 1.0  # a singular test: no evidence of a bend
    keep = values > _RANK_TOLERANCE * max(float(values.max()), 0.0)
    if not keep.any():
        return 1.0 if np.allclose(diff, 0.0) else 0.0
    projected = vectors[:, keep].T @ diff
    statistic = float((projected**2 / values[keep]).sum())
    return float(special.chdtrc(int(keep.sum()), statistic))


def judged_checks(check: IntrinsicsCheck) -> list[IntrinsicsCheck]:
    """The tests whose power and exclusion judge ``check``'s pass: the whole set's alone,
    unless it has an unguided test whose estimate shows guided matching bent the whole
    set's (:func:`guided_bias_p_value` below :data:`GUIDED_BIAS_LEVEL`): then both, and
    the weaker decides."""
    if check.unguided is None or guided_bias_p_value(check) >= GUIDED_BIAS_LEVEL:
        return [check]
    return [check, check.unguided]


def detection_power(check: IntrinsicsCheck, theta: Array) -> float:
    """Probability that ``check``'s test refuses a camera ``theta`` (2,) off the given one
    (see the module docstring), the smallest of its judged tests' powers
    (:func:`judged_checks`)."""
    return min(_power(c, theta) for c in judged_checks(check))


def exclusion_p_value(check: IntrinsicsCheck, theta: Array) -> float:
    """P-value of "the camera is ``theta`` (2,) off the given one" on ``check``'s data: the
    model-based component's Hotelling statistic of ``theta_hat - theta`` (``F(2, dof)``,
    covariance as :func:`detection_power` takes it); the largest of its judged tests'
    (:func:`judged_checks`: each must exclude ``theta``)."""
    return max(_exclusion_p(c, theta) for c in judged_checks(check))


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
    return stats.ncf.sf(limit, 2, dof, scale * max(lam, 0.0))
