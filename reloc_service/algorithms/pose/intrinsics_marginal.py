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

The prior is trusted where the query claims the camera of the keyframes behind the pose: the
map was built with that calibration. A query that claims another camera may carry a stale
one, which the marginal covariance and its envelope of missed errors cover
(:func:`.map_consistency.covariance_with_intrinsics`, :mod:`.intrinsics_power`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .base import PoseEstimate
from .intrinsics import IntrinsicsCheck, Solution

Array = npt.NDArray[np.float64]

#: Offsets (metres and radians) below which two solutions are one pose found twice.
SAME_POSE = 1e-3


def intrinsics_posterior(theta_hat: Array, data_covariance: Array, prior_covariance: Array
                         ) -> tuple[Array, Array]:
    """(2,) mean ``m`` and (2, 2) covariance ``S`` of the intrinsics error given the data's
    estimate ``theta_hat`` (covariance ``data_covariance``, V) and a trusted calibration
    prior ``N(0, prior_covariance)`` (P): two measurements of one unknown, combined by
    their information, ``S = (P^-1 + V^-1)^-1``, ``m = S V^-1 theta_hat`` (Gelman et al.,
    Bayesian Data Analysis, 3.5)."""
    data_info = np.linalg.inv(data_covariance)
    posterior = np.linalg.inv(np.linalg.inv(prior_covariance) + data_info)
    return posterior @ data_info @ np.asarray(theta_hat, np.float64), posterior


def calibration_trusted_covariance(trusted_covariance: Array, check: IntrinsicsCheck) -> Array:
    """(6, 6) the expected squared error of a pose at the given intrinsics where the
    calibration is trusted within its prior ``P`` (the query claims the camera of the
    keyframes behind the pose, which the map vouches for) and the test passed:
    ``trusted_covariance`` is ``d C + B P B^T``; the prior and the data's estimate combine
    (:func:`intrinsics_posterior`) into ``d C + B (S + m m^T) B^T``. No stale-calibration
    envelope: the map was built with this calibration. The solutions the data cannot
    exclude mix in by their posterior weights, likelihood times prior
    (:func:`trusted_solution_weights`): a focal several prior sigmas off drops out."""
    shift = check.pose_shift
    prior = check.prior.covariance
    m, s = intrinsics_posterior(check.theta, check.covariance, prior)
    own = np.asarray(trusted_covariance, np.float64) - shift @ prior @ shift.T
    tested = check.solution
    offsets = np.zeros((6, 6))
    for solution, weight in trusted_solution_weights(check):
        offset = shift @ m if solution is tested else solution.twist
        offsets += weight * np.outer(offset, offset)
    out = own + shift @ s @ shift.T + offsets
    return np.asarray(0.5 * (out + out.T), np.float64)


def trusted_solution_weights(check: IntrinsicsCheck) -> list[tuple[Solution, float]]:
    """The tested solution and the others the data cannot exclude (duplicates of the tested
    one left out), each with its normalised posterior weight under the calibration prior:
    ``exp(-LR / 2 - theta^T P^-1 theta / 2)`` (LR the likelihood ratio against the best)."""
    best = min(check.solutions, key=lambda s: s.cost)
    tested = check.solution
    info = np.linalg.inv(check.prior.covariance)
    kept = [s for s in check.solutions if s is tested or (
        check._likelihood_ratio(s, best) <= check._limit
        and np.abs(s.twist - tested.twist).max() >= SAME_POSE)]
    logs = np.array([-0.5 * check._likelihood_ratio(s, best) - 0.5 * float(s.theta @ info @ s.theta)
                     for s in kept])
    weights = np.exp(logs - logs.max())
    return list(zip(kept, (weights / weights.sum()).tolist(), strict=True))


def checked_covariance(estimate: PoseEstimate) -> Array | None:
    """(6, 6) the covariance relative to the map of ``estimate`` whose intrinsics test passed
    or was not run: :func:`calibration_trusted_covariance` where the query claims the camera
    of the keyframes behind the pose, else its ``covariance`` (the intrinsics marginalised,
    :func:`.map_consistency.covariance_with_intrinsics`)."""
    check, trusted = estimate.intrinsics, estimate.covariance_given_intrinsics
    if (estimate.query_camera_is_map_calibration and trusted is not None
            and check is not None and check.passed):
        return calibration_trusted_covariance(trusted, check)
    return estimate.covariance
