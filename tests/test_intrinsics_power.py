"""What the intrinsics test misses: the noncentrality at which it misses an error at the chosen
rate, a passing pose's covariance that holds every such error's pose shift within 3 sigma,
and a chain step whose test is too weak to vouch for its pose heard only with a later step's
opinion when that step matches other features."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from chain_steps import AnsweringStep
from scipy import stats
from test_pose_intrinsics import ROOM, correspondences

from reloc_service.algorithms.pose.intrinsics import REFUSAL, IntrinsicsCheck
from reloc_service.algorithms.pose.intrinsics_power import (
    blind_spot_factor,
    estimate_underpowered,
    governing_covariance,
    missed_noncentrality,
)
from reloc_service.algorithms.pose.map_consistency import covariance_with_intrinsics
from reloc_service.algorithms.pose.pnp import solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.algorithms.relocalizers.base import (
    Relocalizer,
    RelocResult,
    VerifyConf,
    intrinsics_unchecked,
    verify,
)
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer
from reloc_service.algorithms.relocalizers.inlier_coverage import inlier_cells, on_one_plane
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.frame import Frame
from reloc_service.core.map import KeyframeMap


@pytest.mark.parametrize("missed", [0.5, 0.1, 0.01])
def test_an_error_at_the_missed_noncentrality_passes_at_the_missed_rate(missed):
    lam = missed_noncentrality(1e-3, missed)
    limit = stats.chi2.isf(1e-3, 2)
    # The statistic of an error with that noncentrality: |theta + noise|^2 in units of W.
    rng = np.random.default_rng(0)
    theta = np.array([np.sqrt(lam), 0.0])
    t2 = ((theta + rng.normal(size=(200_000, 2))) ** 2).sum(axis=1)
    assert np.mean(t2 <= limit) == pytest.approx(missed, abs=0.005)
    # Larger errors are missed less often: the noncentrality grows as the rate falls.
    assert lam > missed_noncentrality(1e-3, min(0.9, 2 * missed))


def test_no_error_is_missed_less_often_than_the_test_accepts_a_right_one():
    assert missed_noncentrality(1e-3, 0.9995) == 0.0


def judged(px, points, camera, conf: PnPConf | None = None):
    solved = solve_pnp_indexed(px, points, camera, conf or PnPConf())
    assert solved is not None
    est = solved[0]
    check = est.intrinsics_test()
    assert check is not None and est.covariance is not None
    return est, check


def with_missed(check: IntrinsicsCheck, missed: float) -> IntrinsicsCheck:
    return dataclasses.replace(check, prior=dataclasses.replace(check.prior,
                                                                missed_detection=missed))


def test_a_passing_pose_covers_every_error_its_test_misses_within_3_sigma():
    """The pose shift ``B theta`` of any ``theta`` on the boundary of what the test misses
    at the missed-detection rate lies within 3 sigma of the stated covariance; with the
    expected squared error alone (no widening) it does not."""
    px, points = correspondences(ROOM, 40, 1.5, np.random.default_rng(3), spread=0.6)
    est, check = judged(px, points, ROOM)
    assert check.passed
    stated = covariance_with_intrinsics(est.covariance, check)
    unwidened = covariance_with_intrinsics(est.covariance, with_missed(check, 0.99))
    assert blind_spot_factor(check) > 1.4 and blind_spot_factor(with_missed(check, 0.99)) == 1.0
    w = governing_covariance(check)
    lam = missed_noncentrality(check.prior.false_refusal, check.prior.missed_detection)
    angles = np.linspace(0.0, np.pi, 90, endpoint=False)
    unit = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    # theta on the ellipse theta^T W^-1 theta = lambda
    boundary = np.sqrt(lam) * unit @ np.linalg.cholesky(w).T
    shifts = boundary @ check.pose_shift[:3].T
    m_stated = np.sqrt(np.einsum("ni,ij,nj->n", shifts, np.linalg.inv(stated[:3, :3]), shifts))
    m_before = np.sqrt(np.einsum("ni,ij,nj->n", shifts, np.linalg.inv(unwidened[:3, :3]),
                                 shifts))
    assert m_stated.max() <= 3.0 + 1e-9
    assert m_before.max() > 3.2


def settled(est, check):
    """``est`` judged as a pose finder judges it (:func:`.map_consistency.settle_intrinsics`
    on a map whose keyframes agree with their camera)."""
    est.intrinsics = check
    est.covariance_given_intrinsics = covariance_with_intrinsics(est.covariance, check,
                                                                 trusted=True)
    est.covariance = covariance_with_intrinsics(est.covariance, check)
    return est


def weakly_checked_estimate(rng: np.random.Generator):
    """A pose from 30 coarse keypoints (3 px) on the central 40 % of the image whose
    intrinsics test passes while the data cannot exclude a focal that moves it beyond 3
    sigma: most such views give one (a scene with depth seen through a narrow window)."""
    for _ in range(10):
        est, check = judged(*correspondences(ROOM, 30, 3.0, rng, spread=0.4), ROOM)
        if check.passed and estimate_underpowered(settled(est, check)):
            return est
    raise AssertionError("no underpowered view in 10 draws")


class _FailingSift(Relocalizer):
    """A SIFT step that verifies no pose (so it weighs no contender): every query fails
    with ``reason``."""

    name = "failing"
    method = "failing:sift"
    reason = "too few inliers (3 < 12)"
    required_features = frozenset({"sift"})

    def add_keyframe(self, keyframe) -> None:
        pass

    def remove_keyframe(self, keyframe) -> None:
        pass

    def relocalize(self, query, *, prior=None, hypotheses=1) -> RelocResult:
        return RelocResult.failure(self.method, self.reason)


class _RefusingSift(_FailingSift):
    """A SIFT step that refuses every query's intrinsics."""

    name = "refusing"
    method = "refusing:sift"
    reason = f"{REFUSAL}: focal 400.0 px estimated, 460.0 given (p = 1.0e-06)"


def query_frame() -> Frame:
    return Frame(np.zeros((ROOM.height, ROOM.width), np.uint8), ROOM)


def test_an_underpowered_answer_is_left_to_a_step_with_other_features():
    """An ORB step's pose whose test lacks power is heard only with the SIFT step's
    opinion: a SIFT refusal of the camera answers, not the ORB pose; a pose whose test has
    the power answers at once."""
    rng = np.random.default_rng(4)
    weak = weakly_checked_estimate(rng)
    kmap = KeyframeMap()
    result = ChainRelocalizer(kmap, [AnsweringStep(kmap, weak, kind="orb"),
                                     _RefusingSift(kmap)]).relocalize(
        query_frame())
    assert not result.ok and result.method == "refusing:sift"
    assert result.reason.startswith(REFUSAL)
    # With the same features after it, the step's own test is all there is: it answers.
    same = ChainRelocalizer(kmap, [AnsweringStep(kmap, weak, kind="sift"), _RefusingSift(kmap)])
    assert same.relocalize(query_frame()).ok
    # A test with the power to vouch for the pose: the ORB answer stands.
    strong_est = settled(*judged(*correspondences(ROOM, 400, 0.3, rng), ROOM))
    assert not estimate_underpowered(strong_est)
    result = ChainRelocalizer(kmap, [AnsweringStep(kmap, strong_est, kind="orb"),
                                     _RefusingSift(kmap)]).relocalize(query_frame())
    assert result.ok and result.method == "answering:orb"


def test_an_underpowered_contender_no_later_step_weighs_is_refused_where_asked():
    """An ORB pose whose test lacks power, held for the SIFT step's opinion: where that
    step verifies nothing, the contender answers by default; with
    ``refuse_unweighed_underpowered`` it is refused, saying why and what the later step
    said. A pose whose test has the power answers either way."""
    rng = np.random.default_rng(4)
    weak = weakly_checked_estimate(rng)
    kmap = KeyframeMap()
    on = MultiRelocalizer.Conf(refuse_unweighed_underpowered=True)
    held = ChainRelocalizer(kmap, [AnsweringStep(kmap, weak, kind="orb"), _FailingSift(kmap)])
    assert held.relocalize(query_frame()).ok
    refused = ChainRelocalizer(kmap, [AnsweringStep(kmap, weak, kind="orb", conf=on),
                                      _FailingSift(kmap)]).relocalize(query_frame())
    assert not refused.ok and refused.method == "answering:orb"
    assert "intrinsics unconfirmed" in refused.reason and "too few inliers" in refused.reason
    strong_est = settled(*judged(*correspondences(ROOM, 400, 0.3, rng), ROOM))
    strong = ChainRelocalizer(kmap, [AnsweringStep(kmap, strong_est, kind="orb", conf=on),
                                     _FailingSift(kmap)]).relocalize(query_frame())
    assert strong.ok and strong.method == "answering:orb"


def test_a_view_off_one_plane_that_cannot_check_the_intrinsics_is_refused():
    """15 coarse keypoints (2 px) on the central 30 % of a scene with depth: the view
    cannot bound the focal (the covariance marginalising it would exceed the verification's
    largest position sigma), yet its points are not one plane, where no view could. Trusting
    the calibration there would answer a stale one with the calibration's covariance: even
    a relocalizer's last step refuses it. (A plane seen face on is still answered: see
    test_chain's plane seen face on.)"""
    rng = np.random.default_rng(0)
    for _ in range(40):
        est, check = judged(*correspondences(ROOM, 15, 2.0, rng, spread=0.3), ROOM)
        if not check.passed:
            continue
        est = settled(est, check)
        if (intrinsics_unchecked(est, VerifyConf().max_position_sigma_m)
                and not on_one_plane(est.inlier_points_world, est.inlier_sigmas_m)
                and inlier_cells(est, 4) >= 4):
            break
    else:
        raise AssertionError("no unchecked view off one plane in 40 draws")
    ok, reason, _ = verify(est, VerifyConf(trust_unchecked_intrinsics=True))
    assert not ok and reason.startswith("intrinsics unchecked")
