"""algorithms/pose/intrinsics_envelope.py: a grown pose whose guided matches agree with a stale
claimed focal states a covariance that also covers what its unguided matches say about the
focal; decisions keep their covariance."""

from __future__ import annotations

import dataclasses

import numpy as np
from test_intrinsics_guided import claimed_focal
from test_intrinsics_marginal import settled_estimate
from test_pose_intrinsics import POSE, ROOM, correspondences

from reloc_service.algorithms.pose.decision_covariance import decision_covariance
from reloc_service.algorithms.pose.intrinsics_envelope import (
    intrinsics_moment,
    positive_part,
    unguided_widening,
)
from reloc_service.algorithms.pose.intrinsics_guided import with_unguided_test
from reloc_service.algorithms.pose.map_consistency import covariance_with_intrinsics
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.algorithms.relocalizers.base import stated_covariance
from reloc_service.core.cameras import Camera
from reloc_service.core.geometry import invert, transform_points
from reloc_service.tools.eval import metrics


def bent_correspondences(camera: Camera, claimed: Camera, rng: np.random.Generator, *,
                         seeds: int = 12, seed_noise_px: float = 2.0, guided: int = 150
                         ) -> tuple[np.ndarray, np.ndarray]:
    """A pose grown under a stale focal: ``seeds`` matches found without a pose (the true
    pixels ``camera`` sees, ``seed_noise_px`` noise), then ``guided`` look-alikes found where
    ``claimed`` projects their landmarks from the pose that best explains the image with it
    (the pose at the given intrinsics, fitted to every landmark without noise), 0.5 px
    noise: they agree with the claimed focal by construction. (N, 2) pixels, (N, 3) points,
    the unguided ones first."""
    px_seed, points_seed = correspondences(camera, seeds, seed_noise_px, rng)
    every = correspondences(camera, 300, 0.0, rng)
    fitted = solve_pnp_indexed(*every, claimed, PnPConf(intrinsics_false_refusal=0.0,
                                                        max_reproj_error_px=50.0))
    assert fitted is not None
    world_from_bent = fitted[0].world_from_cam
    _, points_guided = correspondences(camera, guided, 0.0, rng)
    px_guided = claimed.project(transform_points(invert(world_from_bent), points_guided))
    px_guided = px_guided + rng.normal(0.0, 0.5, px_guided.shape)
    return np.concatenate([px_seed, px_guided]), np.concatenate([points_seed, points_guided])


def judged(px: np.ndarray, points: np.ndarray, claimed: Camera, seeds: int):
    """The pose solved on every correspondence at ``claimed``, its intrinsics test with the
    first ``seeds`` as the unguided matches, and the covariance the answer stated without
    the envelope (the intrinsics marginalised on the whole set)."""
    solved = solve_pnp_indexed(px, points, claimed, PnPConf())
    assert solved is not None
    est = solved[0]
    test = with_unguided_test(est.intrinsics_test, np.arange(seeds))
    assert test is not None and est.covariance is not None
    check = test()
    marginal = None if check is None else covariance_with_intrinsics(est.covariance, check)
    return est, check, marginal


def test_the_positive_part_bounds_both_moments():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = (m @ m.T for m in rng.normal(size=(2, 6, 6)))
        both = a + positive_part(b - a)
        assert np.linalg.eigvalsh(both - a).min() > -1e-9
        assert np.linalg.eigvalsh(both - b).min() > -1e-9
    # Where the second is no larger in any direction, nothing is added.
    assert np.allclose(positive_part(-np.eye(3)), 0.0)


def test_guided_matches_that_bend_the_focal_leave_the_true_pose_within_the_envelope():
    """At a focal claimed 5 % too long, a dozen noisy unguided matches cannot refuse it, and
    150 look-alikes found through the claimed camera pull the whole set's focal estimate to
    the claimed one: without the envelope every such answer puts the true pose beyond 7 of
    its stated sigmas. With it, the stated covariance covers what the unguided matches
    estimate (the focal about 5 % short), and the true pose lies within 3 sigma of most."""
    claimed = claimed_focal(ROOM, 1.05)
    before, after = [], []
    for seed in range(30):
        px, points = bent_correspondences(ROOM, claimed, np.random.default_rng(seed))
        est, check, marginal = judged(px, points, claimed, 12)
        if check is None or check.unguided is None or not check.passed:
            continue  # refused (the unguided matches saw the focal), or nothing to test
        assert abs(check.focal_scale - 1.0) < 0.01  # bent to the claimed focal
        widening = unguided_widening(check)
        assert widening is not None
        before.append(metrics.translation_mahalanobis(est.world_from_cam, POSE, marginal))
        after.append(metrics.translation_mahalanobis(est.world_from_cam, POSE,
                                                     marginal + widening))
    assert len(before) >= 10
    assert min(before) > 7.0
    assert all(a < b for a, b in zip(after, before, strict=True))
    assert np.median(after) < 3.0


def test_the_envelope_is_what_the_unguided_matches_state_where_they_know_more():
    """The widened moment is at least both tests' moments: the whole set's (nothing stated
    is lost) and the unguided matches' (their estimate and its uncertainty covered)."""
    claimed = claimed_focal(ROOM, 1.05)
    px, points = bent_correspondences(ROOM, claimed, np.random.default_rng(1))
    _, check, _ = judged(px, points, claimed, 12)
    assert check is not None and check.unguided is not None and check.passed
    shift = check.pose_shift
    widening = unguided_widening(check)
    assert widening is not None
    whole, alone = intrinsics_moment(check, shift), intrinsics_moment(check.unguided, shift)
    assert np.linalg.eigvalsh(whole + widening - alone).min() > -1e-9 * np.abs(alone).max()
    assert np.linalg.eigvalsh(widening).min() > -1e-12


def test_no_unguided_test_or_a_refusal_adds_nothing():
    px, points = correspondences(ROOM, 200, 0.5, np.random.default_rng(2))
    solved = solve_pnp_indexed(px, points, ROOM, PnPConf())
    assert solved is not None and solved[0].intrinsics_test is not None
    check = solved[0].intrinsics_test()
    assert check is not None and check.passed and check.unguided is None
    assert unguided_widening(check) is None
    claimed = claimed_focal(ROOM, 1.15)
    px, points = correspondences(ROOM, 200, 0.5, np.random.default_rng(2))
    refused = with_unguided_test(solve_pnp_indexed(px, points, claimed, PnPConf())[0]
                                 .intrinsics_test, np.arange(60))()
    assert refused is not None and not refused.passed
    assert unguided_widening(refused) is None


def test_the_answer_states_the_envelope_and_the_decision_does_not_read_it():
    claimed = claimed_focal(ROOM, 1.05)
    px, points = bent_correspondences(ROOM, claimed, np.random.default_rng(1))
    est, check, _ = judged(px, points, claimed, 12)
    est = settled_estimate(est, check, map_calibration=False)
    decided = decision_covariance(est, intrinsics_unchecked=False)
    plain = stated_covariance(est, 0.2)
    est.stated_unguided_intrinsics = True
    widened = stated_covariance(est, 0.2)
    assert plain is not None and widened is not None and decided is not None
    assert np.allclose(widened - plain, unguided_widening(check))
    assert np.array_equal(decision_covariance(est, intrinsics_unchecked=False), decided)
    # A query claiming the map's own calibration answers with the calibration's posterior,
    # which the envelope leaves alone.
    mapped = dataclasses.replace(est, query_camera_is_map_calibration=True)
    assert np.array_equal(stated_covariance(mapped, 0.2),
                          stated_covariance(dataclasses.replace(
                              mapped, stated_unguided_intrinsics=False), 0.2))


def test_the_option_is_on_by_default():
    assert PnPConf().stated_unguided_intrinsics
