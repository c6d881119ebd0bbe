"""The intrinsics part of a grown pose's stated covariance, widened to what its unguided matches
cannot exclude.

A pose at the given intrinsics is off by ``B theta`` for an intrinsics error ``theta``; where
the query does not claim the map's calibration, the stated covariance marginalises ``theta``
over the second moment the whole inlier set supports,
``M_w = theta_w theta_w^T + V_w + P + (k - 1) W_w``
(:func:`.map_consistency.covariance_with_intrinsics`: estimate, its covariance, the prior and
the test's blind spot). After guided growth (:mod:`.intrinsics_guided`) that estimate is not
evidence against the claimed camera: matches found in windows around the pose projected with
the claimed focal agree with it by construction and pull ``theta_w`` towards zero, and the
guided matches' number shrinks ``V_w`` (7scenes_redkitchen at x1.15, query 9: ``-2.7 +- 1.0
%`` on all 130 inliers against ``-15.1 +- 2.3 %`` on the 30 unguided ones, truth ``-13 %``;
docs/focal_census.md). Only the matches found without the pose are unbiased under either
hypothesis; their moment ``M_u`` (the same formula on the unguided test, the map's dispersion
included, its own blind spot widening for the same selection: an answer is given only where
that test passed too) is what they cannot exclude.

Neither test tells which moment holds (Hausman's comparison lacks the power over the 3-5
grid cells unguided matches occupy), so the stated moment covers both: ``M_w + (M_u -
M_w)_+``, the positive part taken over the eigenvectors of the symmetric difference. It is at
least ``M_w`` (nothing already stated is lost) and at least ``M_u`` in every direction
(``M_w + D_+ >= M_w + D``), and equals ``M_w`` where the unguided matches know the intrinsics
as well. Both moments are taken through the pose's shift ``B`` (the whole
set's pose is the one answered) with each test's farthest unexcluded solution added, as the
stated covariance adds it, and the envelope is taken over the pose's six dimensions;
decisions never read it (:mod:`.decision_covariance`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .intrinsics import IntrinsicsCheck
from .intrinsics_power import blind_spot_factor, governing_covariance

Array = npt.NDArray[np.float64]


def intrinsics_moment(check: IntrinsicsCheck, shift: Array) -> Array:
    """(6, 6) the second moment of the pose error the intrinsics ``check`` leaves a passing
    pose whose shift per unit of ``theta`` is ``shift`` (6, 2):
    ``B (theta theta^T + V + P + (k - 1) W) B^T + s s^T`` (estimate, its covariance with the
    map's dispersion, the calibration prior, the blind-spot widening of
    :func:`.intrinsics_power.blind_spot_factor` on the governing test covariance, and the
    farthest solution ``s`` the data cannot exclude), the part
    :func:`.map_consistency.covariance_with_intrinsics` adds to the pose's own covariance."""
    theta = np.asarray(check.theta, np.float64)
    widening = blind_spot_factor(check) - 1.0
    moment = (np.outer(theta, theta) + check.prior.covariance + check.covariance
              + widening * governing_covariance(check))
    far = np.asarray(check.unexcluded_twist, np.float64)
    out = shift @ moment @ shift.T + np.outer(far, far)
    return np.asarray(0.5 * (out + out.T), np.float64)


def positive_part(symmetric: Array) -> Array:
    """(n, n) the positive semidefinite part of the symmetric ``symmetric``: its eigenvalues
    below zero set to zero. ``A + (B - A)_+`` is then at least both ``A`` and ``B`` in the
    Loewner order."""
    values, vectors = np.linalg.eigh(0.5 * (symmetric + symmetric.T))
    return np.asarray((vectors * np.maximum(values, 0.0)) @ vectors.T, np.float64)


def unguided_widening(check: IntrinsicsCheck) -> Array | None:
    """(6, 6) what the stated covariance of a pose whose intrinsics test ``check`` passed
    lacks of what its unguided matches cannot exclude about the intrinsics:
    ``(M_u - M_w)_+``, ``M`` the moments of :func:`intrinsics_moment` of the unguided
    matches' test and of the whole set's, both through the pose's shift ``B`` (the pose
    answered is the whole set's). None where there is no unguided test (the pose was not
    grown, or its unguided matches were too few to test) or no finite moment."""
    if check.unguided is None or not check.passed:
        return None
    shift = np.asarray(check.pose_shift, np.float64)
    if not np.all(np.isfinite(shift)):
        return None
    difference = intrinsics_moment(check.unguided, shift) - intrinsics_moment(check, shift)
    if not np.all(np.isfinite(difference)):
        return None
    return positive_part(difference)
