"""Whether a tracked pose agrees with the prior it was matched from: the twist from the
prior to the answer, Mahalanobis under the sum of both covariances, within the chi-square
gate of 6 degrees of freedom. A pose outside it contradicts the prior whose windows chose
its matches."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core import distributions as stats
from ...core.geometry import invert, se3_log

Array = npt.NDArray[np.float64]


def within_prior(answer_world_from_cam: Array, answer_covariance: Array | None,
                 prior_world_from_cam: Array, prior_covariance: Array, probability: float
                 ) -> bool:
    """Whether the answer (4x4 ``answer_world_from_cam``, its (6, 6) covariance or None:
    none stated) lies inside the prior's ``probability`` gate: the twist from the prior to
    the answer, Mahalanobis under the sum of both covariances, within
    ``chi2_6(probability)``."""
    xi = se3_log(invert(prior_world_from_cam) @ answer_world_from_cam)
    total = np.asarray(prior_covariance, np.float64) + (
        0.0 if answer_covariance is None else answer_covariance)
    try:
        m2 = float(xi @ np.linalg.solve(total, xi))
    except np.linalg.LinAlgError:
        m2 = float(xi @ np.linalg.pinv(total) @ xi)
    return m2 <= float(stats.chi2.ppf(probability, 6))
