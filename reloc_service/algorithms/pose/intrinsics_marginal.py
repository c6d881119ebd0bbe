"""The expected squared error a pose estimated at the given intrinsics owes to them, where
the calibration is trusted within its prior.

The pose at the given camera is off by ``B theta`` (:attr:`.intrinsics.IntrinsicsCheck.pose_shift`)
when the camera is really ``theta`` off. Two pieces of information bound ``theta``: the
calibration prior ``theta ~ N(0, P)`` and the pose's own correspondences, which estimate it
as ``theta_hat`` with covariance ``V`` (the map's dispersion included), independently of the
pose's noise at the given camera (the Schur complement splits the joint normal equations
so). They are two measurements of one unknown and combine by their information:
``theta | data ~ N(m, S)``, and the expected squared shift ``B (S + m m^T) B^T`` averages to
``B P B^T`` over queries whose calibration is as good as its prior says. Adding ``P``, ``V``
and ``theta_hat theta_hat^T`` instead counts the data's noise twice and the prior once more.

The prior ``P`` here is the map's stated calibration accuracy
(:attr:`.base.PoseEstimate.calibration_covariance`, the map's configuration), not the
tolerance the intrinsics test allows (:attr:`.intrinsics.IntrinsicsCheck.prior`): a map of a
camera calibrated exactly (a rendered dataset) states ``P = 0`` and the pose at the given
intrinsics with no calibration part, while its test keeps refusing what it refused. Only
what an answer states reads it.

The prior is trusted where the query claims the camera of the keyframes behind the pose: the
map was built with that calibration. A query that claims another camera may carry a stale
one, which the marginal covariance and its envelope of missed errors cover
(:func:`.map_consistency.covariance_with_intrinsics`, :mod:`.intrinsics_power`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .base import PoseEstimate
from .cell_sandwich import widened
from .intrinsics import IntrinsicsCheck, Solution
from .intrinsics_envelope import unguided_widening

Array = npt.NDArray[np.float64]

#: Offsets (metres and radians) below which two solutions are one pose found twice.
SAME_POSE = 1e-3


def intrinsics_posterior(theta_hat: Array, data_covariance: Array, prior_covariance: Array
                         ) -> tuple[Array, Array]:
    """(2,) mean ``m`` and (2, 2) covariance ``S`` of the intrinsics error given the data's
    estimate ``theta_hat`` (covariance ``data_covariance``, V) and a trusted calibration
    prior ``N(0, prior_covariance)`` (P): two measurements of one unknown, combined by
    their information, ``S = (P^-1 + V^-1)^-1``, ``m = S V^-1 theta_hat`` (Gelman et al.,
    Bayesian Data Analysis, 3.5), computed in the equivalent gain form ``G = P (P + V)^-1``,
    ``m = G theta_hat``, ``S = P - G P``, which holds for an exact calibration too
    (``P = 0``: ``m = 0``, ``S = 0``)."""
    prior = np.asarray(prior_covariance, np.float64)
    gain = np.linalg.solve((prior + np.asarray(data_covariance, np.float64)).T, prior.T).T
    posterior = prior - gain @ prior
    mean = np.asarray(gain @ np.asarray(theta_hat, np.float64), np.float64)
    return mean, np.asarray(0.5 * (posterior + posterior.T), np.float64)


def calibration_prior(estimate: PoseEstimate, check: IntrinsicsCheck) -> Array:
    """(2, 2) the calibration covariance ``estimate``'s answer trusts: the map's stated one
    where known, else the prior the intrinsics test allowed."""
    stated = estimate.calibration_covariance
    return check.prior.covariance if stated is None else np.asarray(stated, np.float64)


def calibration_trusted_covariance(trusted_covariance: Array, check: IntrinsicsCheck,
                                   calibration: Array | None = None) -> Array:
    """(6, 6) the expected squared error of a pose at the given intrinsics where the
    calibration is trusted within ``calibration`` ``P`` (2, 2; default the test's prior)
    (the query claims the camera of the keyframes behind the pose, which the map vouches
    for) and the test passed: ``trusted_covariance`` is ``d C + B P_t B^T`` (``P_t`` the
    test's prior); the prior and the data's estimate combine (:func:`intrinsics_posterior`)
    into ``d C + B (S + m m^T) B^T``. No stale-calibration envelope: the map was built with
    this calibration. The solutions the data cannot exclude mix in by their posterior
    weights, likelihood times prior (:func:`trusted_solution_weights`): a focal several
    prior sigmas off drops out."""
    shift = check.pose_shift
    prior = check.prior.covariance if calibration is None else calibration
    own = own_covariance(trusted_covariance, check)
    m, s = intrinsics_posterior(check.theta, check.covariance, prior)
    tested = check.solution
    offsets = np.zeros((6, 6))
    for solution, weight in trusted_solution_weights(check, prior):
        offset = shift @ m if solution is tested else solution.twist
        offsets += weight * np.outer(offset, offset)
    out = own + shift @ s @ shift.T + offsets
    return np.asarray(0.5 * (out + out.T), np.float64)


def own_covariance(trusted_covariance: Array, check: IntrinsicsCheck) -> Array:
    """(6, 6) ``d C``: the pose's covariance at exact intrinsics (the map's dispersion
    ``d`` included), ``trusted_covariance`` (``d C + B P_t B^T``) without the test's
    prior ``P_t``."""
    shift = check.pose_shift
    return np.asarray(trusted_covariance, np.float64) - shift @ check.prior.covariance @ shift.T


def trusted_solution_weights(check: IntrinsicsCheck, prior: Array | None = None
                             ) -> list[tuple[Solution, float]]:
    """The tested solution and the others the data cannot exclude (duplicates of the tested
    one left out), each with its normalised posterior weight under the calibration prior
    ``prior`` (2, 2; default the test's): ``exp(-LR / 2 - theta^T P^-1 theta / 2)`` (LR the
    likelihood ratio against the best). A prior exact along some direction gives no weight
    to a solution off the given camera: the tested one alone."""
    tested = check.solution
    prior = check.prior.covariance if prior is None else np.asarray(prior, np.float64)
    if np.linalg.matrix_rank(prior) < len(prior):
        return [(tested, 1.0)]
    best = min(check.solutions, key=lambda s: s.cost)
    info = np.linalg.inv(prior)
    kept = [s for s in check.solutions if s is tested or (
        check._likelihood_ratio(s, best) <= check._limit
        and np.abs(s.twist - tested.twist).max() >= SAME_POSE)]
    logs = np.array([-0.5 * check._likelihood_ratio(s, best) - 0.5 * float(s.theta @ info @ s.theta)
                     for s in kept])
    weights = np.exp(logs - logs.max())
    return list(zip(kept, (weights / weights.sum()).tolist(), strict=True))


def given_calibration_covariance(estimate: PoseEstimate) -> Array | None:
    """(6, 6) the covariance relative to the map of ``estimate`` at the given intrinsics
    trusted within the map's stated calibration alone (no data on them: a view that cannot
    check them), ``d C + B P B^T``; ``estimate.covariance_given_intrinsics`` (the test's
    prior) where no calibration is stated or no test ran."""
    trusted, check = estimate.covariance_given_intrinsics, estimate.intrinsics
    if trusted is None or check is None or estimate.calibration_covariance is None:
        return trusted
    trusted, check = stated_dispersion_parts(estimate, trusted, check)
    shift = check.pose_shift
    out = own_covariance(trusted, check) + shift @ calibration_prior(estimate, check) @ shift.T
    return np.asarray(0.5 * (out + out.T), np.float64)


def checked_covariance(estimate: PoseEstimate) -> Array | None:
    """(6, 6) the covariance relative to the map of ``estimate`` whose intrinsics test passed
    or was not run: :func:`calibration_trusted_covariance` (under the map's stated
    calibration accuracy) where the query claims the camera of the keyframes behind the
    pose, else its ``covariance`` (the intrinsics marginalised,
    :func:`.map_consistency.covariance_with_intrinsics`), widened where asked
    (:attr:`.base.PoseEstimate.stated_unguided_intrinsics`) to what the unguided matches
    of a grown pose cannot exclude (:func:`.intrinsics_envelope.unguided_widening`)."""
    check, trusted = estimate.intrinsics, estimate.covariance_given_intrinsics
    if (estimate.query_camera_is_map_calibration and trusted is not None
            and check is not None and check.passed):
        trusted, check = stated_dispersion_parts(estimate, trusted, check)
        return calibration_trusted_covariance(trusted, check, calibration_prior(estimate, check))
    if estimate.covariance is None or check is None or not estimate.stated_unguided_intrinsics:
        return estimate.covariance
    extra = unguided_widening(check)
    return estimate.covariance if extra is None else np.asarray(estimate.covariance + extra,
                                                                np.float64)


def stated_dispersion_parts(estimate: PoseEstimate, trusted: Array, check: IntrinsicsCheck
                            ) -> tuple[Array, IntrinsicsCheck]:
    """``trusted`` (``d C + B P_t B^T``) and ``check`` with the decision's dispersion ``d``
    replaced by the one the answer states (:attr:`.base.PoseEstimate.stated_dispersion`,
    robust to mis-associated map landmarks): ``d_s C + B P_t B^T`` and ``V`` scaled by
    ``d_s``; then ``d_s C`` widened to the spread the inliers show over the image's cells
    where it exceeds it (:attr:`.base.PoseEstimate.measurement_sandwich`,
    :func:`.cell_sandwich.widened`); unchanged where neither applies."""
    if estimate.stated_dispersion is not None:
        stated = check.with_dispersion(estimate.stated_dispersion)
        ratio = stated.dispersion / check.dispersion
        trusted = trusted + (ratio - 1.0) * own_covariance(trusted, check)
        check = stated
    sandwich = None if estimate.measurement_sandwich is None else estimate.measurement_sandwich()
    if sandwich is not None:
        own = own_covariance(trusted, check)
        trusted = trusted + widened(own, *sandwich) - own
    return np.asarray(0.5 * (trusted + trusted.T), np.float64), check
