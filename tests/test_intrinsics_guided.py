"""The intrinsics test of a pose grown by guided matching: matches found around the
projections of a wrong-focal pose confirm the focal they were found with, so the matches found
without the pose are tested alone too, and the given camera passes only where both agree."""

from __future__ import annotations

import dataclasses

import numpy as np
from test_pose_intrinsics import ROOM, correspondences

from reloc_service.algorithms.pose.intrinsics import REFUSAL
from reloc_service.algorithms.pose.intrinsics_guided import (
    unguided_positions,
    with_unguided_test,
)
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.core.cameras import Camera
from reloc_service.core.geometry import invert, transform_points


def claimed_focal(camera: Camera, scale: float) -> Camera:
    """``camera`` claiming ``scale`` times its focal (a stale calibration)."""
    return dataclasses.replace(camera, fx=camera.fx * scale, fy=camera.fy * scale)


def grown_correspondences(camera: Camera, claimed: Camera, rng: np.random.Generator
                          ) -> tuple[np.ndarray, np.ndarray, int]:
    """What guided matching gives under a stale calibration on a repeated texture: 60 matches
    found without a pose (the true pixels of their points, taken with ``camera``), then 200
    found in windows around the projections, through ``claimed``, from the pose ``claimed``
    fits to the central unguided ones (look-alike keypoints where the wrong camera predicts
    the landmarks). (N, 2) pixels, (N, 3) points and the number of unguided ones (first)."""
    px_seed, points_seed = correspondences(camera, 60, 0.5, rng)
    central = correspondences(camera, 40, 0.5, rng, spread=0.35)
    solved = solve_pnp_indexed(*central, claimed, PnPConf(intrinsics_false_refusal=0.0))
    assert solved is not None
    world_from_wrong = solved[0].world_from_cam
    _, points_guided = correspondences(camera, 200, 0.0, rng)
    px_guided = claimed.project(transform_points(invert(world_from_wrong), points_guided))
    px_guided = px_guided + rng.normal(0.0, 0.5, px_guided.shape)
    return (np.concatenate([px_seed, px_guided]), np.concatenate([points_seed, points_guided]),
            len(px_seed))


def test_unguided_positions_are_the_pairs_found_without_the_pose():
    query_idx = np.array([4, 7, 9, 2, 5])
    pool_rows = np.array([10, 3, 8, 1, 6])
    # (7, 3) and (2, 1) are seed pairs; (9, 8) is not (keypoint 9 was matched to row 0);
    # (5, 6) is not either (a seed row of -1: a landmark the pool lacks matches nothing).
    seed_q, seed_rows = np.array([7, 9, 2, 5]), np.array([3, 0, 1, -1])
    assert unguided_positions(query_idx, pool_rows, seed_q, seed_rows).tolist() == [1, 3]
    assert len(unguided_positions(query_idx, pool_rows, seed_q[:0], seed_rows[:0])) == 0


def test_guided_matches_cannot_overrule_the_unguided_ones_on_a_stale_focal():
    claimed = claimed_focal(ROOM, 1.15)
    px, points, seeds = grown_correspondences(ROOM, claimed, np.random.default_rng(3))
    solved = solve_pnp_indexed(px, points, claimed, PnPConf())
    assert solved is not None and solved[0].intrinsics_test is not None
    whole = solved[0].intrinsics_test()
    assert whole is not None
    # On every match the guided ones outvote the rest: the given focal passes (the old verdict).
    assert whole.passed
    test = with_unguided_test(solved[0].intrinsics_test, np.arange(seeds))
    assert test is not None
    check = test()
    assert check is not None and check.unguided is not None
    # Alone, the unguided matches see the camera that took the image: 1 / 1.15 of the claim.
    assert abs(check.unguided.focal_scale - 1.0 / 1.15) < 0.01
    assert not check.passed
    assert check.reason.startswith(f"{REFUSAL}: focal ")
    assert check.reason.endswith("on the matches found without the pose")


def test_the_given_camera_passes_both_tests():
    rng = np.random.default_rng(4)
    px, points = correspondences(ROOM, 260, 0.5, rng)
    solved = solve_pnp_indexed(px, points, ROOM, PnPConf())
    assert solved is not None
    test = with_unguided_test(solved[0].intrinsics_test, np.arange(60))
    assert test is not None
    check = test()
    assert check is not None and check.unguided is not None
    assert check.passed and check.reason == ""
    # The dispersion of the map reaches both tests.
    assert check.with_dispersion(2.5).unguided.dispersion == 2.5


def test_a_subset_test_on_every_row_is_the_whole_test():
    px, points = correspondences(ROOM, 120, 0.5, np.random.default_rng(5))
    solved = solve_pnp_indexed(px, points, claimed_focal(ROOM, 1.05), PnPConf())
    assert solved is not None and solved[0].intrinsics_test is not None
    whole, same = solved[0].intrinsics_test(), solved[0].intrinsics_test(rows=np.arange(120))
    assert whole is not None and same is not None
    assert np.allclose(whole.theta, same.theta) and whole.p_value == same.p_value


def test_no_test_stays_no_test():
    assert with_unguided_test(None, np.arange(3)) is None


def test_an_unguided_test_does_not_weaken_the_whole_sets():
    """Adding the unguided test keeps the whole set's at its own level: a whole-set p-value
    between half the level and the level still refuses (a stale focal on repeated-hard
    at 1.3 had p = 7.5e-4 on every match and none to say on its unguided ones)."""
    px, points = correspondences(ROOM, 260, 0.5, np.random.default_rng(7))
    solved = solve_pnp_indexed(px, points, ROOM, PnPConf())
    assert solved is not None
    check = with_unguided_test(solved[0].intrinsics_test, np.arange(60))()
    assert check is not None and check.unguided is not None and check.unguided.passed
    level = check.prior.false_refusal
    solution = dataclasses.replace(check.solution, robust_covariance=None)
    direction = np.array([1.0, 0.0])

    def p_at(size: float) -> float:
        moved = dataclasses.replace(solution, theta=size * direction)
        return dataclasses.replace(check, solutions=(moved,)).p_value

    low, high = 0.0, 1.0  # bisect the focal error whose p-value is 0.75 of the level
    for _ in range(60):
        mid = (low + high) / 2
        low, high = (mid, high) if p_at(mid) > 0.75 * level else (low, mid)
    moved = dataclasses.replace(solution, theta=low * direction)
    whole = dataclasses.replace(check, solutions=(moved,))
    assert level / 2 < whole.p_value < level
    assert not whole.passed
    assert whole.reason.startswith(f"{REFUSAL}: focal ")
