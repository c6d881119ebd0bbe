"""Whether two intrinsics tests of one query, on different correspondences, estimate the same
focal: a two-sample test of their estimates.

Two steps of a chain that match the same kind of keypoints to the same map estimate the
query's focal error ``a`` (the focal ``1 + a`` times the given one, :mod:`.intrinsics`) on
different correspondences. Both estimate the one camera that took the image, so where both
are unbiased their difference is zero up to their noise: ``t^2 = (a_1 - a_2)^2 / (v_1 +
v_2)`` (``v``: each test's model variance of ``a``, scaled by the map's dispersion) is
``F(1, dof)`` with the smaller of the two residual degrees of freedom. The calibration prior
does not enter: it is the given camera's error, common to both, and cancels in the
difference. Errors the two share (the same landmarks seen by both) make the difference's
variance smaller than ``v_1 + v_2``, so the test is conservative there. As in the
intrinsics test itself, a region whose landmarks share their errors is allowed for by the
cluster-robust variances (``r_1 + r_2`` over ``G``, the fewer occupied cells, against
``F(1, G - 1)``): the estimates disagree only where both components reject.

The focal alone is compared, not the radial term: the radial estimates of two SIFT steps
differ by more than their stated noise with the right camera (tum_fr1_rpy query 5: bow+p3p
and sbi+p3p 29 px apart at the image corner, 4.2 of their sigmas, both poses within 1 cm),
while their focal estimates agree within theirs on every query of tum_fr1_rpy and
7scenes_redkitchen (the closest: 3.6 sigma by the model, 2.6 by the cluster-robust
variance).

The same holds within one step whose pose was grown by guided matching: its unguided
matches are a subset of the whole set, so under "guided matching did not bend the focal"
the difference of the two focal estimates has variance ``v_u - v_w`` (Hausman 1978, as
:func:`.intrinsics_confirmation.guided_bias_p_value` tests both components; the focal alone
here, for the reason above): :func:`guided_bend_p_value` (7scenes_redkitchen query 9 with a
focal 15 % long: bow+p3p's 30 unguided inliers estimate -15.1 +- 2.3 %, its 130 inliers
grown around the pose -2.7 +- 1.0 %, chi-square 36; the pose 33 cm off at 4.2 sigma).

Estimates that disagree cannot both be of a correct pose at the camera they claim: one of
the two poses absorbed a focal error the other measured (a pose moved along its axis
explains the centre of an image taken with another focal, :mod:`.intrinsics`). Nothing in
the two tests says which, so a pose whose pass disagrees with another step's estimate is
no confirmation of the given camera (tum_fr1_rpy query 8 with a focal 15 % long: bow+p3p's
140 inliers estimate +1.6 +- 2.8 % and pass, sift-half's 76 estimate -15.1 +- 1.8 % and
refuse; bow's pose is 13 cm off, 3.7 of its sigmas).

That reading holds for two estimates of ONE pose hypothesis. A pose on another copy of a
repeated picture (or any other place) estimates whatever focal maps that copy's scale onto
the image, which says nothing of the camera (the clean repeated set's query 39 with the right
camera: bow+p3p's pose, 0.3 mm off, estimates +0.0 +- 0.1 %; sift-half's refused pose 1.2 m
away on another copy of the picture, -18.6 +- 2.1 %). Whether two poses are one hypothesis
once their focal difference is allowed for: each pose at the given camera moves by ``-B
theta`` (:attr:`.intrinsics.IntrinsicsCheck.pose_shift`, right perturbation) to the pose at a
camera ``theta`` off, so at a common camera ``theta`` the twist between them is ``d(theta) =
d_0 + (B_1 - B_2) theta`` (``d_0`` the twist from the first to the second at the given
camera; to first order, both frames one). With their covariances summed (each relative to
the world: the keyframes' errors included) the smallest squared Mahalanobis length over
``theta`` (generalised least squares) is chi-square with ``6 - rank(B_1 - B_2)`` degrees of
freedom where they are one hypothesis: :func:`same_hypothesis_p_value`. A disagreement
with a pose of another hypothesis is no test of the focal but of which place is right, left
to the caller (:mod:`..relocalizers.confirmation`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy import special

from ...core.geometry import se3_log
from .base import PoseEstimate, total_covariance
from .intrinsics import IntrinsicsCheck

Array = npt.NDArray[np.float64]


def disagreement_p_value(first: IntrinsicsCheck, second: IntrinsicsCheck) -> float:
    """P-value of "``first`` and ``second`` estimate the same focal": the larger of the
    model-based two-sample test's (variance ``v_1 + v_2``, ``F(1, dof)`` with the smaller
    dof) and the cluster-robust one's (``r_1 + r_2``, ``F(1, G - 1)`` over ``G``, the fewer
    occupied cells), as the module docstring says. 1 where a variance is not positive and
    finite (no evidence)."""
    diff = float(first.theta[0]) - float(second.theta[0])
    one, two = first.solution, second.solution
    p_model = _f1_p_value(diff, first.covariance[0, 0] + second.covariance[0, 0],
                          min(one.dof, two.dof))
    if one.robust_covariance is None or two.robust_covariance is None:
        return p_model
    robust = one.robust_covariance[0, 0] + two.robust_covariance[0, 0]
    return max(p_model, _f1_p_value(diff, robust, min(one.clusters, two.clusters) - 1))


def guided_bend_p_value(check: IntrinsicsCheck, *, one_sigma: bool = False) -> float:
    """P-value of "guided matching did not bend ``check``'s focal estimate": Hausman's
    ``(a_u - a_w)^2 / (v_u - v_w)`` of its unguided and whole-set estimates, chi-square with
    1 degree of freedom (see the module docstring). 1 without an unguided test, or where the
    unguided focal is no less precise than the whole set's (nothing to test against).

    ``one_sigma``: both variances from one residual variance, the unguided set's (``v_w``
    times ``sigma_u^2 / sigma_w^2``). Under the null both sets' residuals are one noise;
    guided matches that fit a wrong focal inflate the whole set's own variance until ``v_w``
    reaches ``v_u`` and the test sees nothing (repeated-hard with a focal 15 % long, query
    50: bow+p3p's whole set +0.6 +- 1.7 % at 1.24 px, its 12 unguided inliers -11.3 +- 1.7 %
    at 0.45 px; p = 1 by each set's own variance, 1e-13 by one)."""
    unguided = check.unguided
    if unguided is None:
        return 1.0
    diff = float(unguided.theta[0]) - float(check.theta[0])
    whole = float(check.covariance[0, 0])
    if one_sigma:
        whole *= unguided.solution.sigma2 / check.solution.sigma2
    gap = float(unguided.covariance[0, 0]) - whole
    if not (np.isfinite(gap) and gap > 0.0):
        return 1.0
    return float(special.chdtrc(1, diff * diff / gap))


def _f1_p_value(diff: float, variance: float, dof: int) -> float:
    """``P(F(1, dof) > diff^2 / variance)``; 1 without evidence (a variance that is not
    positive and finite, or no degree of freedom)."""
    if not (np.isfinite(variance) and variance > 0.0) or dof < 1:
        return 1.0
    return float(special.fdtrc(1, dof, diff * diff / variance))


def first_disagreement(check: IntrinsicsCheck, others: list[IntrinsicsCheck]
                       ) -> tuple[int, float] | None:
    """``(index, p)`` of the first of ``others`` whose estimate disagrees with ``check``'s
    (:func:`disagreement_p_value`) at ``check``'s false-refusal rate shared among the
    comparisons (Bonferroni: with the right camera and unbiased estimates, any of them
    disagrees at most at that rate); None where every one agrees."""
    if not others:
        return None
    level = check.prior.false_refusal / len(others)
    for i, other in enumerate(others):
        p = disagreement_p_value(check, other)
        if p < level:
            return i, p
    return None


def focal_text(check: IntrinsicsCheck) -> str:
    """``check``'s focal estimate relative to the given one, with its sigma: "+1.6 +- 2.8 %"."""
    sigma = float(np.sqrt(max(check.covariance[0, 0], 0.0)))
    return f"{check.theta[0] * 100:+.1f} +- {sigma * 100:.1f} %"


def same_hypothesis_p_value(first: PoseEstimate, second: PoseEstimate) -> float:
    """P-value of "``first`` and ``second`` are one pose hypothesis, at some common camera":
    the smallest squared Mahalanobis length of the twist between them over the camera
    ``theta`` both are moved to (the module docstring), chi-square with ``6 - rank(B_1 -
    B_2)`` degrees of freedom. 1 (no evidence they differ) where either lacks an intrinsics
    test or a covariance, or where the statistic is not finite."""
    a, b = total_covariance(first), total_covariance(second)
    if first.intrinsics is None or second.intrinsics is None or a is None or b is None:
        return 1.0
    d0 = se3_log(np.linalg.inv(first.world_from_cam) @ second.world_from_cam)
    shift = first.intrinsics.pose_shift - second.intrinsics.pose_shift
    try:
        chol = np.linalg.cholesky(a + b)
        white_d = np.linalg.solve(chol, d0)
        white_m = np.linalg.solve(chol, shift)
    except np.linalg.LinAlgError:
        return 1.0
    if not (np.all(np.isfinite(white_d)) and np.all(np.isfinite(white_m))):
        return 1.0
    theta, _, rank, _ = np.linalg.lstsq(white_m, -white_d, rcond=None)
    residual = white_d + white_m @ theta
    return float(special.chdtrc(6 - int(rank), float(residual @ residual)))
