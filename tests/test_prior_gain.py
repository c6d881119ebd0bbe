"""A tracked pose must predict its inliers' pixels more precisely than its prior did
(``algorithms/pose/prior_gain.py``): the image variance ``trace(H C)`` of a pose covariance
is the pixel variance it gives the points, and a tracked pose no better determined than the
prior in what the image sees is left to the method."""

from __future__ import annotations

import numpy as np

from reloc_service.algorithms.pose.prior_gain import (
    image_information,
    image_variance_ratio,
    largest_variance_ratio,
    narrower_everywhere,
    narrows_prior,
    stated_and_unique,
)
from reloc_service.algorithms.relocalizers.base import Prior
from reloc_service.algorithms.relocalizers.factory import create_relocalizer, create_tracker
from reloc_service.algorithms.relocalizers.tracking import TRACK
from reloc_service.algorithms.relocalizers.tracking_fallback import relocalize_with_prior
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import (
    pose_covariance_from_sigmas,
    pose_error,
    se3_exp,
    transform_points,
)
from reloc_service.core.map import KeyframeMap

CAMERA = PinholeCamera(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)


def _wall(depth_m: float, rng: np.random.Generator) -> np.ndarray:
    """(200, 3) points on a wall ``depth_m`` in front of an identity camera, in view."""
    xy = rng.uniform(-0.5, 0.5, (200, 2)) * depth_m * np.array([640.0, 480.0]) / 500.0
    return np.column_stack([xy, depth_m + rng.normal(0, 0.05 * depth_m, 200)])


def test_image_variance_is_the_pixel_variance_a_covariance_gives_the_points():
    rng = np.random.default_rng(0)
    points = _wall(3.0, rng)
    cov = pose_covariance_from_sigmas(0.01, np.deg2rad(0.2))
    cov[0, 4] = cov[4, 0] = -0.6 * np.sqrt(cov[0, 0] * cov[4, 4])  # a correlated pair
    # Monte Carlo: the pixels of the points seen from poses drawn from ``cov`` (right
    # perturbations of the identity), their summed squared shift.
    base = CAMERA.project(points)
    shifts = [CAMERA.project(transform_points(np.linalg.inv(se3_exp(xi)), points)) - base
              for xi in rng.multivariate_normal(np.zeros(6), cov, 3000)]
    expected = float(np.mean([np.sum(s**2) for s in shifts]))
    predicted = float(np.trace(image_information(CAMERA, np.eye(4), points) @ cov))
    assert abs(predicted / expected - 1.0) < 0.05


def test_a_move_the_image_cannot_see_neither_fails_nor_passes_an_answer():
    rng = np.random.default_rng(1)
    points = _wall(10.0, rng)                      # a facade 10 m away
    prior = pose_covariance_from_sigmas(0.05, np.deg2rad(2.0))
    # Sharp in every direction but along the optical axis, where it is twice as uncertain
    # as the prior: a 10 cm move along the axis shifts a pixel by at most ~3 px here.
    along_axis = np.diag([0.005, 0.005, 0.10, 1e-4, 1e-4, 1e-4]) ** 2
    assert narrows_prior(CAMERA, np.eye(4), points, along_axis, prior)
    # Less certain than the prior in rotation (3 against 2 degrees): every pixel moves.
    turned = np.diag([0.005, 0.005, 0.005, *np.deg2rad([3.0, 3.0, 3.0])]) ** 2
    assert not narrows_prior(CAMERA, np.eye(4), points, turned, prior)
    assert image_variance_ratio(CAMERA, np.eye(4), points, turned, prior) > 2.0
    assert not narrows_prior(CAMERA, np.eye(4), points, None, prior)


def test_the_largest_variance_ratio_is_the_worst_direction_of_the_answer_against_the_prior():
    rng = np.random.default_rng(2)
    prior = pose_covariance_from_sigmas(0.05, np.deg2rad(2.0))
    # An answer sharp everywhere but 3x the prior's sigma along one (random) direction.
    basis, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    scales = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 3.0])
    root = np.linalg.cholesky(prior)
    answer = root @ basis @ np.diag(scales**2) @ basis.T @ root.T
    assert abs(largest_variance_ratio(answer, prior) - 9.0) < 1e-9
    # Brute force over directions: no direction's variance ratio exceeds it, and the worst
    # one reaches it.
    dirs = rng.normal(size=(20000, 6))
    ratios = (np.einsum("ni,ij,nj->n", dirs, answer, dirs)
              / np.einsum("ni,ij,nj->n", dirs, prior, dirs))
    assert ratios.max() <= 9.0 + 1e-9
    worst = np.linalg.solve(root.T, basis[:, 5])
    assert abs(float(worst @ answer @ worst / (worst @ prior @ worst)) - 9.0) < 1e-9
    assert not narrower_everywhere(answer, prior)
    assert narrower_everywhere(0.9 * prior, prior)
    assert not narrower_everywhere(None, prior)


def test_an_answer_worse_than_the_prior_along_the_axis_fails_every_direction_only():
    # The facade of the test above: 10 cm along the axis against the prior's 5 cm passes the
    # image average (the pixels hardly move) but not the test in every direction.
    rng = np.random.default_rng(1)
    points = _wall(10.0, rng)
    prior = pose_covariance_from_sigmas(0.05, np.deg2rad(2.0))
    along_axis = np.diag([0.005, 0.005, 0.10, 1e-4, 1e-4, 1e-4]) ** 2
    assert narrows_prior(CAMERA, np.eye(4), points, along_axis, prior)
    assert not narrower_everywhere(along_axis, prior)
    assert narrower_everywhere(np.diag([0.005, 0.005, 0.04, 1e-4, 1e-4, 1e-4]) ** 2, prior)


def _query(scene, i):
    return Frame(scene.query_images[i], scene.camera)


def test_a_focal_the_data_pin_down_is_no_reason_to_leave_a_tracked_pose_to_the_method(
        synthetic_scene, synthetic_map):
    # A sharp VIO prior (1 cm, 0.3 degree) and a camera whose focal is known to 5 % only.
    # The decision covariance doubts that calibration (the focal free, its prior added on
    # top): 5 % of the scene's depth along the axis, above the prior's 1 cm, so under
    # "every direction" tracking verifies but refuses and the method answers. The room's
    # depth pins the focal down: the answer's stated covariance (the calibration's prior
    # and the data's estimate combined) is millimetres along the axis, and its farthest
    # unexcluded solution near, so under the default it is tracked, and right.
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    gt = synthetic_scene.query_poses[0]
    prior = Prior(gt @ se3_exp(np.r_[0.006, -0.004, 0.008, 0.0, 0.003, -0.002]),
                  covariance=pose_covariance_from_sigmas(0.01, np.deg2rad(0.3)))
    doubting = create_tracker(kmap, options={"track": {"focal_sigma_rel": 0.05,
                                                       "narrowing": "every direction"}})
    refused = doubting.relocalize(_query(synthetic_scene, 0), prior=prior)
    assert not refused.ok and "no better than the prior (every direction)" in refused.reason
    method = create_relocalizer("sbi+p3p", kmap)
    method.train()
    answer = relocalize_with_prior(method, doubting, _query(synthetic_scene, 0), prior=prior)
    assert answer.ok and answer.method == "sbi+p3p"
    tracker = create_tracker(kmap, options={"track": {"focal_sigma_rel": 0.05}})
    tracked = tracker.relocalize(_query(synthetic_scene, 0), prior=prior)
    assert tracked.ok and tracked.method == TRACK, tracked.reason
    dt, dr = pose_error(tracked.world_from_cam, gt)
    assert dt < 0.005 and dr < np.deg2rad(0.1)
    assert tracked.covariance[2, 2] < prior.covariance[2, 2]
    # With the calibration known to 0.5 % (the default) the image average narrows the same
    # prior too; the decision covariance still not along the axis (0.5 % of a few metres
    # is more than the prior's 1 cm).
    average = create_tracker(kmap, options={"track": {"narrowing": "image average"}})
    assert average.relocalize(_query(synthetic_scene, 0), prior=prior).ok
    every = create_tracker(kmap, options={"track": {"narrowing": "every direction"}})
    refused = every.relocalize(_query(synthetic_scene, 0), prior=prior)
    assert not refused.ok and "(every direction)" in refused.reason
    assert create_tracker(kmap).relocalize(_query(synthetic_scene, 0), prior=prior).ok


def test_a_solution_the_data_cannot_exclude_beyond_the_priors_sigma_fails_the_default():
    rng = np.random.default_rng(3)
    prior = pose_covariance_from_sigmas(0.05, np.deg2rad(2.0))
    stated = 0.3 * prior
    direction = np.linalg.cholesky(prior) @ rng.normal(size=6)
    unit = direction / np.sqrt(direction @ np.linalg.solve(prior, direction))  # 1 prior sigma
    # The ratio along the far solution's direction is 0.3 + (its prior sigmas)^2.
    near, far = 0.8 * unit, 0.9 * unit
    assert abs(largest_variance_ratio(stated_and_unique(stated, near, True), prior)
               - (0.3 + 0.64)) < 1e-9
    assert narrower_everywhere(stated_and_unique(stated, near, True), prior)
    assert not narrower_everywhere(stated_and_unique(stated, far, True), prior)
    # Where the calibration was not trusted, the stated covariance is the decision's, which
    # holds the far solution already: it is not counted twice.
    assert narrower_everywhere(stated_and_unique(stated, far, False), prior)
    assert narrower_everywhere(stated_and_unique(stated, None, True), prior)


def test_a_tracked_pose_sharper_than_its_prior_is_answered(synthetic_scene, synthetic_map):
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    gt = synthetic_scene.query_poses[0]
    prior = Prior(gt @ se3_exp(np.r_[0.03, -0.02, 0.04, 0.0, 0.02, -0.01]),
                  covariance=pose_covariance_from_sigmas(0.05, np.deg2rad(2.0)))
    tracked = create_tracker(kmap).relocalize(_query(synthetic_scene, 0), prior=prior)
    assert tracked.ok and tracked.method == TRACK, tracked.reason


def test_an_unknown_answer_covariance_narrows_nothing():
    """A tracked pose from a singular fit (an infinite covariance) is no better known than
    its prior in any direction."""
    prior = pose_covariance_from_sigmas(0.05, np.deg2rad(2.0))
    unknown = np.full((6, 6), np.inf)
    assert largest_variance_ratio(unknown, prior) == np.inf
    assert not narrower_everywhere(unknown, prior)
