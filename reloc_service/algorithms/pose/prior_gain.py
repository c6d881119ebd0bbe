"""Whether a tracked pose is better determined than the prior it was matched from, as the
image sees it.

A tracked pose rests on matches drawn from windows the prior placed: along a direction in
which the matches determine the pose less well than the prior did, the windows (the prior),
not the image, chose them, and the pose there is the prior's information handed back with
the matches' noise on top. The comparison is made where the windows live, in the image: the
variance a pose covariance ``C`` gives the projections of the answer's inliers,
``sum_i trace(J_i C J_i^T) = trace(H C)`` with ``H = sum_i J_i^T J_i`` (``J_i`` the (2, 6)
Jacobian of inlier ``i``'s pixel w.r.t. a right perturbation of ``world_from_cam``). Each
pose direction counts by how far it moves the inliers' pixels, so a direction the image
cannot see (a move along the optical axis of a camera 10 m from a facade shifts no pixel
by much) neither fails nor passes an answer, whatever its variance there. The answer
narrows the prior when ``trace(H C_answer) < trace(H C_prior)``: its predicted windows
are smaller on average than the prior's were. ``C_answer`` is what this image owes the
pose (its matches and its camera's calibration), not the keyframes' pose errors a prior
anchored to the same map shares. Since ``trace(H (sigma^2 H^-1)) = 6 sigma^2`` for a pose
fixed by its ``N`` keypoints alone (noise ``sigma``), such a pose narrows any prior whose
mean pixel variance over the inliers exceeds ``6 sigma^2 / N``: what fails is a pose whose
calibration (or its keyframe groups' spread) leaves it less certain than a sharp prior.

That average lets a direction the inliers' pixels hardly move hide behind the sharp ones,
and an answer that passes it can still be less certain than the prior along that direction:
on 7-Scenes (1-3 m depth, ORB inliers on part of the image) the tracked answers that pass
the average yet state 7-17 cm along one axis, above the prior's 5 cm, are 6-20 cm from the
truth (Mahalanobis 5-12 under their own covariance, with 2-5 degrees of rotation error),
where the chain without the prior answers within 4 cm. The stricter test,
:func:`narrower_everywhere`, asks the answer's covariance to lie below the prior's in the
Loewner order: ``u^T C_answer u < u^T C_prior u`` for every pose direction ``u``, the
largest generalised eigenvalue of ``(C_answer, C_prior)`` below 1. A pose that is no better
known than the prior along some direction holds there only what the windows the prior
placed gave it, and the image's own answer (the method, matching without the prior) decides.

Which covariance of the answer is compared matters. The decision covariance (what the
verification refuses by) doubts the calibration: the focal is a free unknown, the test's
calibration prior is added on top, and so is the data's estimate of a focal error. Along the
optical axis of a facade ~10 m away that alone exceeds a 5 cm prior (Strecha: 0.55-2.3 of its
variance), though the windows choose no match by it and the method's answer carries the same.
:func:`stated_and_unique` compares instead what the answer states (the calibration trusted
within the map's stated accuracy and combined with what the data say of it), plus the
farthest solution the data cannot exclude as a variance: where the data admit another pose
about as well beyond the prior's one sigma, which of the two the windows found was the
prior's choice. The tracked 7-Scenes and TUM answers 5-20 cm off state less than the prior
in most directions, but each has such a solution 0.8-3.4 prior sigmas away, and with it
lies above the prior (largest ratio 1.16-11.5; the tracked answers within 5 cm: at most 0.96).

Both covariances are twists of a right perturbation, the answer's at the answer and the
prior's at the prior; within the prior's gate the two frames differ by a few degrees, a
first-order difference left out."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.geometry import invert, transform_points
from .projection import pose_jacobian

Array = npt.NDArray[np.float64]


def image_information(camera: Camera, world_from_cam: Array, points_world: Array) -> Array:
    """(6, 6) ``H = sum_i J_i^T J_i`` of (N, 3) ``points_world`` seen from
    ``world_from_cam`` (pixels^2 per unit twist; the points in front of the camera)."""
    points_cam = transform_points(invert(world_from_cam), points_world)
    points_cam = points_cam[points_cam[:, 2] > 0]
    if len(points_cam) == 0:
        return np.zeros((6, 6))
    jac = pose_jacobian(camera, points_cam)  # (2N, 6)
    return jac.T @ jac


def image_variance_ratio(camera: Camera, world_from_cam: Array, points_world: Array,
                         answer_covariance: Array, prior_covariance: Array) -> float:
    """``trace(H C_answer) / trace(H C_prior)`` over the inliers (N, 3) ``points_world``
    of the answer ``world_from_cam``: below 1 where the answer predicts its inliers'
    pixels more precisely than the prior did; inf where the prior predicts them exactly."""
    info = image_information(camera, world_from_cam, points_world)
    prior = float(np.trace(info @ np.asarray(prior_covariance, np.float64)))
    answer = float(np.trace(info @ np.asarray(answer_covariance, np.float64)))
    return answer / prior if prior > 0 else float("inf")


def narrows_prior(camera: Camera, world_from_cam: Array, points_world: Array,
                  answer_covariance: Array | None, prior_covariance: Array) -> bool:
    """Whether the answer (its (6, 6) ``answer_covariance``; None: unknown, not
    narrower) predicts the pixels of its inliers ``points_world`` more precisely than the
    prior's ``prior_covariance`` did (:func:`image_variance_ratio` below 1)."""
    if answer_covariance is None or len(points_world) == 0:
        return False
    return image_variance_ratio(camera, world_from_cam, points_world, answer_covariance,
                                prior_covariance) < 1.0


def largest_variance_ratio(answer_covariance: Array, prior_covariance: Array) -> float:
    """``max_u (u^T C_answer u) / (u^T C_prior u)`` over pose directions ``u``: the largest
    eigenvalue of ``L^-1 C_answer L^-T`` with ``C_prior = L L^T`` (both (6, 6)); inf where
    the prior's covariance is singular (a direction it knows exactly) or the answer's is not
    finite (a singular fit: unknown)."""
    try:
        chol = np.linalg.cholesky(np.asarray(prior_covariance, np.float64))
    except np.linalg.LinAlgError:
        return float("inf")
    white = np.linalg.solve(chol, np.linalg.solve(chol, np.asarray(answer_covariance,
                                                                  np.float64)).T)
    if not np.all(np.isfinite(white)):
        return float("inf")
    return float(np.linalg.eigvalsh(0.5 * (white + white.T)).max())


def narrower_everywhere(answer_covariance: Array | None, prior_covariance: Array) -> bool:
    """Whether the answer's (6, 6) ``answer_covariance`` (None: unknown, not narrower) lies
    below the prior's ``prior_covariance`` in every pose direction
    (:func:`largest_variance_ratio` below 1)."""
    if answer_covariance is None:
        return False
    return largest_variance_ratio(answer_covariance, prior_covariance) < 1.0


def stated_and_unique(stated_own_covariance: Array, unexcluded_twist: Array | None,
                      calibration_trusted: bool) -> Array:
    """(6, 6) what :func:`narrower_everywhere` compares with the prior under
    ``narrowing = "stated, unique"``: the covariance the answer states relative to the map
    (``stated_own_covariance``, the keyframes' part left out), plus, where that trusted the
    map's calibration (``calibration_trusted``: it then weighs the solutions the data
    cannot exclude by the calibration's prior, and a focal several sigmas off drops out),
    the (6,) ``unexcluded_twist`` of the farthest such solution as a variance ``s s^T``, as
    the decision covariance counts it. Where the data admit another pose about as well,
    which of the two the prior's windows found was the prior's choice: the sum lies below
    the prior's covariance only if that other pose lies within the prior's one-sigma
    ellipsoid (``s^T C_prior^-1 s < 1``) and the stated covariance is below it too. Where
    the calibration is not trusted, the stated covariance is the decision's, which holds
    ``s s^T`` already."""
    out = np.asarray(stated_own_covariance, np.float64)
    if calibration_trusted and unexcluded_twist is not None:
        far = np.asarray(unexcluded_twist, np.float64)
        out = out + np.outer(far, far)
    return out
