"""The covariance a verification decision weighs a pose by, kept apart from the one it answers with.

An answer states the covariance a filter should fuse: for a query that claims the map's own
calibration, the calibration prior and the data's intrinsics estimate combined
(:func:`.intrinsics_marginal.checked_covariance`), which is right on average over queries
whose calibration is as good as its prior says. A decision is a test, and a test must keep
its error rate under the alternative it guards against, where that prior is not to be
trusted: "position too uncertain" refuses a pose whose correspondences cannot pin it down,
and the poses it must refuse (a consensus on a repeated picture, a view where the focal and
the distance trade off, a lens changed since the mapping) are those whose intrinsics error
the prior does not describe. So the decision weighs the pose with the intrinsics left free
unknowns bounded by what the data cannot exclude, the prior added as a further independent
error rather than combined with the data (:func:`.map_consistency.covariance_with_intrinsics`
without ``trusted``), plus the keyframe poses' errors. That statistic reads only the
measurements, the keyframe poses and the intrinsics test, never how the answer's covariance
is assembled, so a change to the stated covariance cannot change which pose answers.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .base import PoseEstimate, total_covariance

Array = npt.NDArray[np.float64]


def decision_covariance(estimate: PoseEstimate, *, intrinsics_unchecked: bool) -> Array | None:
    """(6, 6) the covariance relative to the world by which a verification judges
    ``estimate``: its marginal covariance (``estimate.covariance``: the intrinsics
    marginalised without trusting the calibration, as the pose finder settled it), or
    where its view cannot check the intrinsics (``intrinsics_unchecked``) the calibration's
    (``estimate.covariance_given_intrinsics``: its prior alone, the only bound there is);
    plus the keyframe poses' errors (:func:`.base.total_covariance`). None without a
    covariance."""
    if intrinsics_unchecked:
        return total_covariance(estimate, estimate.covariance_given_intrinsics)
    return total_covariance(estimate)
