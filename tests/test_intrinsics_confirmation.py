"""A passing intrinsics test confirms the given camera against an error another test estimated
only with the power to see it; a chain step's pose after an earlier step's refusal of the
query's intrinsics answers only then."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from chain_steps import AnsweringStep, RefusingOrb
from test_pose_intrinsics import ROOM, correspondences

from reloc_service.algorithms.pose.intrinsics import REFUSAL, IntrinsicsCheck
from reloc_service.algorithms.pose.intrinsics_confirmation import (
    GUIDED_BIAS_LEVEL,
    confirms,
    detection_power,
    excludes,
    exclusion_p_value,
    guided_bias_p_value,
    judged_checks,
    refused_theta,
)
from reloc_service.algorithms.pose.map_consistency import covariance_with_intrinsics
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.algorithms.relocalizers.base import (
    RelocResult,
)
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.frame import Frame
from reloc_service.core.map import KeyframeMap
from reloc_service.tools.eval.query_camera import QueryCamera

#: The camera a stale calibration claims: the focal 1.3 times the one that took the images.
STALE = QueryCamera(focal_scale=1.3).claimed(ROOM)


def judged(px, points, camera):
    """The pose of ``px`` on ``points`` through ``camera``, with its intrinsics test settled
    as a pose finder settles it (on a map whose keyframes agree with their camera)."""
    solved = solve_pnp_indexed(px, points, camera, PnPConf())
    assert solved is not None
    est = solved[0]
    check = est.intrinsics_test()
    assert check is not None and est.covariance is not None
    est.intrinsics = check
    est.covariance_given_intrinsics = covariance_with_intrinsics(est.covariance, check,
                                                                 trusted=True)
    est.covariance = covariance_with_intrinsics(est.covariance, check)
    return est


@pytest.fixture(scope="module")
def stale_refusal() -> IntrinsicsCheck:
    """300 sharp keypoints over the whole image, claimed through the stale camera: refused,
    the focal estimated 1 / 1.3 of the claimed one."""
    check = judged(*correspondences(ROOM, 300, 0.5, np.random.default_rng(0)), STALE).intrinsics
    assert check is not None and not check.passed
    assert 1.0 + refused_theta(check)[0] == pytest.approx(1 / 1.3, abs=0.01)
    return check


def weak_pass(camera, rng: np.random.Generator):
    """A pose from 20 coarse keypoints (3 px) on the central 40 % of the image whose test
    passes: where the camera is stale, such views pass (a focal 30 % off fits nearly as well
    from a pose moved along the axis)."""
    for _ in range(10):
        est = judged(*correspondences(ROOM, 20, 3.0, rng, spread=0.4), camera)
        if est.intrinsics.passed:
            return est
    raise AssertionError("no passing view in 10 draws")


def test_a_weak_pass_under_a_stale_focal_cannot_confirm_it(stale_refusal):
    """The weak view's test passes the stale camera: its data is too coarse to see the
    refused error (at it, its statistic would exceed the level less than half the time)."""
    est = weak_pass(STALE, np.random.default_rng(0))
    power = detection_power(est.intrinsics, refused_theta(stale_refusal))
    assert power < 0.5
    assert not confirms(est.intrinsics, stale_refusal)


def test_a_sharp_pass_at_the_true_focal_confirms_it(stale_refusal):
    """400 sharp keypoints at the true camera: the test would refuse a focal 23 % off
    almost surely, so its pass overrules the refusal (a biased estimate of the refusing
    step's)."""
    est = judged(*correspondences(ROOM, 400, 0.3, np.random.default_rng(1)), ROOM)
    assert est.intrinsics.passed
    assert detection_power(est.intrinsics, refused_theta(stale_refusal)) > 0.99
    assert excludes(est.intrinsics, refused_theta(stale_refusal))
    assert confirms(est.intrinsics, stale_refusal)
    # A refused test confirms nothing, whatever its power.
    assert not confirms(stale_refusal, stale_refusal)


def near_pass_and_refusal() -> tuple[IntrinsicsCheck, IntrinsicsCheck]:
    """A refusal estimating the focal 2.8 % short (300 sharp keypoints, the focal claimed 3 %
    long) and a pass estimating it 1.4 % short (300 keypoints of 1 px, claimed 1.5 % long):
    the pass has the precision to see the refused error but its own estimate lies near it."""
    refusal = judged(*correspondences(ROOM, 300, 0.5, np.random.default_rng(0)),
                     QueryCamera(focal_scale=1.03).claimed(ROOM)).intrinsics
    near = judged(*correspondences(ROOM, 300, 1.0, np.random.default_rng(1)),
                  QueryCamera(focal_scale=1.015).claimed(ROOM)).intrinsics
    assert not refusal.passed and near.passed
    return near, refusal


def test_a_pass_near_the_refused_error_does_not_exclude_it_and_cannot_confirm():
    """Failing to reject the given camera is not excluding the refused one: a pass whose
    test would see the refused error almost surely, but whose estimate lies within its
    noise of that error, leaves the refusal standing (the validation room under a focal
    30 % long: a pass at -19 % against a refusal at -23 %, power 0.99, pose 1.2 m off)."""
    near, refusal = near_pass_and_refusal()
    theta = refused_theta(refusal)
    assert detection_power(near, theta) > 0.9
    assert exclusion_p_value(near, theta) > near.prior.false_refusal
    assert not excludes(near, theta)
    assert not confirms(near, refusal)


def test_exclusion_is_certain_far_from_the_estimate_and_absent_at_it():
    near, _ = near_pass_and_refusal()
    assert exclusion_p_value(near, near.theta) == pytest.approx(1.0)
    assert excludes(near, near.theta + np.array([0.2, 0.0]))
    # Coarse matches cannot exclude it (where such unguided matches show guided matching
    # bent the whole set, they keep it: the test below of a bent guided set).
    weak = weak_pass(STALE, np.random.default_rng(0)).intrinsics
    assert not excludes(weak, near.theta + np.array([0.2, 0.0]))


def test_power_grows_with_the_error_and_is_the_level_at_none(stale_refusal):
    est = judged(*correspondences(ROOM, 400, 0.3, np.random.default_rng(1)), ROOM)
    check = est.intrinsics
    powers = [detection_power(check, np.array([a, 0.0])) for a in (0.0, 0.005, 0.02, 0.1)]
    assert powers[0] <= check.prior.false_refusal * 1.0001
    assert np.all(np.diff(powers) > 0) and powers[-1] > 0.99


def _confirm(confirm: bool) -> MultiRelocalizer.Conf:
    """The multi relocalizer's options with ``confirm_intrinsics``."""
    return MultiRelocalizer.Conf(confirm_intrinsics=confirm)


def _chain(refusal: IntrinsicsCheck, estimate, confirm: bool = True) -> RelocResult:
    kmap = KeyframeMap()
    chain = ChainRelocalizer(kmap, [RefusingOrb(kmap, refusal),
                                    AnsweringStep(kmap, estimate, conf=_confirm(confirm))])
    return chain.relocalize(Frame(np.zeros((ROOM.height, ROOM.width), np.uint8), STALE))


def test_a_later_pose_without_the_power_leaves_the_refusal_standing(stale_refusal):
    """Under the stale camera, the later step's weakly tested pose does not overrule the
    earlier refusal: the chain refuses, naming both steps."""
    weak = weak_pass(STALE, np.random.default_rng(0))
    result = _chain(stale_refusal, weak)
    assert not result.ok and result.method == "refusing:orb"
    assert result.reason.startswith(REFUSAL)
    assert "answering:sift cannot confirm the given intrinsics" in result.reason
    # With confirm_intrinsics off (on by default), any verified pose overrules the refusal.
    assert _chain(stale_refusal, weak, confirm=False).ok
    assert MultiRelocalizer.Conf().confirm_intrinsics


def test_a_later_pose_near_the_refused_error_leaves_the_refusal_standing():
    near, refusal = near_pass_and_refusal()
    kmap = KeyframeMap()
    est = judged(*correspondences(ROOM, 300, 1.0, np.random.default_rng(1)),
                 QueryCamera(focal_scale=1.015).claimed(ROOM))
    assert est.intrinsics.passed
    chain = ChainRelocalizer(kmap, [RefusingOrb(kmap, refusal),
                                    AnsweringStep(kmap, est, conf=_confirm(True))])
    result = chain.relocalize(Frame(np.zeros((ROOM.height, ROOM.width), np.uint8), STALE))
    assert not result.ok and result.method == "refusing:orb"
    assert "its data reject it at p = " in result.reason


def test_a_later_pose_with_the_power_overrules_the_refusal(stale_refusal):
    sharp = judged(*correspondences(ROOM, 400, 0.3, np.random.default_rng(1)), ROOM)
    result = _chain(stale_refusal, sharp)
    assert result.ok and result.method == "answering:sift"
    assert np.allclose(result.world_from_cam, sharp.world_from_cam)


def test_coarse_unguided_matches_that_agree_with_the_guided_set_do_not_veto_it(stale_refusal):
    """Unguided matches too coarse to see the refused error, whose estimate agrees with the
    whole set's within their noise (Hausman's test does not reject), show no bend by guided
    matching: the whole set's power and exclusion decide, and its pass confirms the camera
    (room-hard query 38 with the right camera)."""
    sharp = judged(*correspondences(ROOM, 400, 0.3, np.random.default_rng(1)), ROOM).intrinsics
    # 20 keypoints of 3 px on the central 20 % of the image, at the right camera.
    coarse = judged(*correspondences(ROOM, 20, 3.0, np.random.default_rng(0), spread=0.2),
                    ROOM).intrinsics
    grown = dataclasses.replace(sharp, unguided=coarse)
    theta = refused_theta(stale_refusal)
    assert detection_power(coarse, theta) < 0.5
    assert guided_bias_p_value(grown) >= GUIDED_BIAS_LEVEL
    assert judged_checks(grown) == [grown]
    assert detection_power(grown, theta) == pytest.approx(detection_power(sharp, theta))
    assert grown.passed and confirms(grown, stale_refusal)


def test_a_guided_set_bent_away_from_its_unguided_matches_is_judged_by_them_too(stale_refusal):
    """A whole set at the given focal whose unguided matches estimate the refused error with
    precision (Hausman's test rejects: guided matching bent the estimate) is judged by the
    weaker of the two: the unguided matches do not exclude the refused error, so the
    whole set's pass cannot confirm the camera."""
    sharp = judged(*correspondences(ROOM, 400, 0.3, np.random.default_rng(1)), ROOM).intrinsics
    bent = dataclasses.replace(sharp, unguided=stale_refusal)
    theta = refused_theta(stale_refusal)
    assert guided_bias_p_value(bent) < GUIDED_BIAS_LEVEL
    assert judged_checks(bent) == [bent, stale_refusal]
    assert excludes(sharp, theta) and not excludes(bent, theta)
    assert not confirms(bent, stale_refusal)


def test_the_guided_bias_test_has_no_say_without_unguided_matches_or_a_difference():
    near, _ = near_pass_and_refusal()
    assert guided_bias_p_value(near) == 1.0 and judged_checks(near) == [near]
    # The same estimate from a less precise subset: no difference, no evidence of a bend.
    same = dataclasses.replace(near, unguided=dataclasses.replace(near, dispersion=4.0))
    assert guided_bias_p_value(same) == pytest.approx(1.0)
