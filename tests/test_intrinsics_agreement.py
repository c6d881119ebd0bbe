"""Two intrinsics tests of one query agree where they estimate the same camera, and a chain
refuses a pose whose estimate disagrees with an earlier step's on the same keypoints."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from chain_steps import AnsweringStep, RefusingOrb
from test_intrinsics_confirmation import STALE, judged
from test_pose_intrinsics import ROOM, correspondences

from reloc_service.algorithms.pose.intrinsics import IntrinsicsCheck
from reloc_service.algorithms.pose.intrinsics_agreement import (
    disagreement_p_value,
    first_disagreement,
    guided_bend_p_value,
    same_hypothesis_p_value,
)
from reloc_service.algorithms.relocalizers.base import (
    RelocResult,
    RelocStatus,
)
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer
from reloc_service.algorithms.relocalizers.confirmation import (
    REFUSAL_BETWEEN_STEPS,
    StepEstimate,
    disagreeing_steps,
)
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.features import FeatureConf
from reloc_service.core.frame import Frame
from reloc_service.core.map import KeyframeMap
from reloc_service.tools.eval.query_camera import QueryCamera


def sharp(camera, seed: int):
    """A pose from 300 sharp keypoints (0.5 px) over the whole image through ``camera``."""
    return judged(*correspondences(ROOM, 300, 0.5, np.random.default_rng(seed)), camera)


@pytest.fixture(scope="module")
def stale_refusal() -> IntrinsicsCheck:
    check = sharp(STALE, 0).intrinsics
    assert check is not None and not check.passed
    return check


def test_independent_estimates_of_one_camera_agree(stale_refusal):
    right = [sharp(ROOM, seed).intrinsics for seed in (1, 2)]
    assert disagreement_p_value(right[0], right[1]) > right[0].prior.false_refusal
    # Under the stale camera both estimate the same error (-23 %): they agree too.
    other_stale = sharp(STALE, 3).intrinsics
    assert disagreement_p_value(stale_refusal, other_stale) > stale_refusal.prior.false_refusal
    assert first_disagreement(right[0], [right[1]]) is None


def test_estimates_of_two_cameras_disagree(stale_refusal):
    right = sharp(ROOM, 1).intrinsics
    p = disagreement_p_value(right, stale_refusal)
    assert p < 1e-6
    assert disagreement_p_value(stale_refusal, right) == pytest.approx(p)  # symmetric
    assert first_disagreement(right, [sharp(ROOM, 2).intrinsics, stale_refusal]) == (1, p)
    assert first_disagreement(right, []) is None


def with_unguided(whole: IntrinsicsCheck, camera, seed: int) -> IntrinsicsCheck:
    """``whole`` with an unguided test on 60 coarser keypoints (1 px) seen through
    ``camera``: fewer and less precise than the whole set, as unguided matches are."""
    alone = judged(*correspondences(ROOM, 60, 1.0, np.random.default_rng(seed)), camera)
    return dataclasses.replace(whole, unguided=alone.intrinsics)


def test_guided_matching_bent_the_focal_where_the_unguided_matches_see_another():
    whole = sharp(ROOM, 1).intrinsics
    assert guided_bend_p_value(whole) == 1.0  # no unguided test: no evidence
    agreeing = with_unguided(whole, ROOM, 4)
    assert guided_bend_p_value(agreeing) > whole.prior.false_refusal
    bent = with_unguided(whole, STALE, 4)
    assert guided_bend_p_value(bent) < 1e-6
    # The other way round (the "unguided" test the more precise) there is nothing to test.
    assert guided_bend_p_value(dataclasses.replace(bent.unguided, unguided=whole)) == 1.0


def _noisier(check: IntrinsicsCheck, factor: float) -> IntrinsicsCheck:
    """``check`` with every solution's residuals ``sqrt(factor)`` times larger (its variance,
    covariance and cost scaled alike, so the same solution is tested)."""
    return dataclasses.replace(check, solutions=tuple(
        dataclasses.replace(s, sigma2=s.sigma2 * factor, cost=s.cost * factor,
                            model_covariance=s.model_covariance * factor)
        for s in check.solutions))


def test_one_residual_variance_sees_a_bend_that_made_the_whole_set_noisier():
    whole = sharp(ROOM, 1).intrinsics
    bent = with_unguided(whole, STALE, 4)
    # Guided matches fitting a wrong focal: the whole set's residuals grow until its focal
    # variance passes the unguided one's, and by each set's own variance nothing is seen.
    noisy = _noisier(bent, 1.05 * float(bent.unguided.covariance[0, 0] / bent.covariance[0, 0]))
    assert guided_bend_p_value(noisy) == 1.0
    assert guided_bend_p_value(noisy, one_sigma=True) < 1e-6
    # One camera: the one-variance test keeps to its level.
    agreeing = with_unguided(whole, ROOM, 4)
    assert guided_bend_p_value(agreeing, one_sigma=True) > whole.prior.false_refusal


class _RefusingSiftHalf(RefusingOrb):
    """The same on SIFT of the half-size query (as the default chain's sift-half)."""

    method = "refusing:sift"
    required_features = frozenset({"sift"})

    def feature_confs(self) -> dict[str, FeatureConf]:
        conf = FeatureConf(kind="sift", scale=0.5)
        return {conf.key: conf}


def _compare(compare: bool, guided: bool = False) -> MultiRelocalizer.Conf:
    """The multi relocalizer's options with ``compare_intrinsics`` and ``compare_guided_focal``."""
    return MultiRelocalizer.Conf(compare_intrinsics=compare, compare_guided_focal=guided)


def _chain(refusal: IntrinsicsCheck, features: str, estimate, compare: bool = True
           ) -> RelocResult:
    kmap = KeyframeMap()
    first = (RefusingOrb if features == "orb" else _RefusingSiftHalf)(kmap, refusal)
    chain = ChainRelocalizer(kmap, [first,
                                    AnsweringStep(kmap, estimate, conf=_compare(compare))])
    return chain.relocalize(Frame(np.zeros((ROOM.height, ROOM.width), np.uint8), STALE))


def test_a_pass_that_disagrees_with_an_earlier_step_on_the_same_keypoints_is_refused(
        stale_refusal):
    """A sharp pose whose test passes the given camera, after a SIFT step whose SIFT
    correspondences estimated another: the two cannot both be right, so the chain refuses,
    naming both estimates (it answered before: the pass has the power to see the refused
    error and its data exclude it)."""
    passing = sharp(ROOM, 1)
    assert passing.intrinsics.passed
    result = _chain(stale_refusal, "sift", passing)
    assert not result.ok and result.method == "answering:sift"
    assert result.reason.startswith(REFUSAL_BETWEEN_STEPS)
    assert "refusing:sift -23." in result.reason
    assert _chain(stale_refusal, "sift", passing, compare=False).ok
    assert MultiRelocalizer.Conf().compare_intrinsics


def test_an_earlier_refusal_on_other_keypoints_is_left_to_the_confirmation(stale_refusal):
    """ORB's estimate carries its pyramid's bias: a SIFT pass that confirms the given camera
    against it (:mod:`..intrinsics_confirmation`) answers."""
    passing = sharp(ROOM, 1)
    result = _chain(stale_refusal, "orb", passing)
    assert result.ok and np.allclose(result.world_from_cam, passing.world_from_cam)



def test_a_pose_whose_guided_matches_bent_the_focal_is_refused_on_request():
    """A pass whose unguided matches estimate another focal: refused where the step asks
    (``compare_guided_focal``, off by default), answered otherwise."""
    bent = sharp(ROOM, 1)
    bent.intrinsics = with_unguided(bent.intrinsics, STALE, 4)
    kmap = KeyframeMap()
    query = Frame(np.zeros((ROOM.height, ROOM.width), np.uint8), ROOM)
    chain = ChainRelocalizer(kmap, [AnsweringStep(kmap, bent, conf=_compare(True, guided=True))])
    result = chain.relocalize(query)
    assert not result.ok and "guided matching bent it" in result.reason
    chain = ChainRelocalizer(kmap, [AnsweringStep(kmap, bent, conf=_compare(True))])
    assert chain.relocalize(query).ok
    assert not MultiRelocalizer.Conf().compare_guided_focal


#: A camera whose focal is 1 / 1.15 of the room camera's: pixels it sees, judged through the
#: room camera, estimate the focal 13 % short, the pose moved along its axis to absorb it.
SHORT = QueryCamera(focal_scale=1 / 1.15).claimed(ROOM)


def _seen(camera, seed: int, offset_m: float = 0.0):
    """A pose judged through the room camera from 300 sharp keypoints that ``camera`` saw,
    their world points moved ``offset_m`` along x (a copy of the scene elsewhere)."""
    px, points = correspondences(camera, 300, 0.5, np.random.default_rng(seed))
    return judged(px, points + np.array([offset_m, 0.0, 0.0]), ROOM)


def test_poses_of_one_place_are_one_hypothesis_whatever_their_focal_estimates():
    """Two estimates of the same place whose focal estimates disagree (one pose moved along
    its axis by a focal 13 % short) are one hypothesis once each is moved by its focal
    sensitivity to a common camera; a pose of a copy of the scene 1 m away is not."""
    right, short = _seen(ROOM, 1), _seen(SHORT, 2)
    assert disagreement_p_value(right.intrinsics, short.intrinsics) < 1e-6
    assert same_hypothesis_p_value(right, short) > right.intrinsics.prior.false_refusal
    elsewhere = _seen(SHORT, 2, offset_m=1.0)
    assert same_hypothesis_p_value(right, elsewhere) < 1e-6
    assert same_hypothesis_p_value(elsewhere, right) < 1e-6


def _answer(estimate) -> RelocResult:
    return RelocResult(status=RelocStatus.OK, method="answering:sift",
                       world_from_cam=estimate.world_from_cam,
                       covariance=estimate.covariance, confidence=0.5)


def test_a_disagreement_with_another_place_is_weighed_as_a_rival():
    """A refused pose of the same place whose focal disagrees refuses the answer whatever
    the weighing says (one of the two absorbed a focal error); a refused pose of another
    place refuses it only where the answer does not explain the query significantly better
    (``weigh`` gives why not), and without ``weigh`` (the option off) as any other."""
    right = _seen(ROOM, 1)
    answer = _answer(right)
    sift = frozenset({"sift"})

    def earlier(estimate) -> list[StepEstimate]:
        return [StepEstimate("refusing:sift", sift, estimate.intrinsics, estimate)]

    def better(first, second) -> None:
        return None

    def comparable(first, second) -> str:
        return "40 vs 250 query keypoints explained by one alone"

    same_place = earlier(_seen(SHORT, 2))
    for weigh in (better, comparable, None):
        refusal = disagreeing_steps(answer, right, sift, same_place, weigh=weigh)
        assert refusal is not None and not refusal.ok
        assert refusal.reason.startswith(REFUSAL_BETWEEN_STEPS)
        assert refusal.reason.endswith("absorbed a focal error")
    elsewhere = earlier(_seen(SHORT, 2, offset_m=1.0))
    assert disagreeing_steps(answer, right, sift, elsewhere, weigh=better) is None
    rival = disagreeing_steps(answer, right, sift, elsewhere, weigh=comparable)
    assert rival is not None and "another place" in rival.reason and "40 vs 250" in rival.reason
    assert disagreeing_steps(answer, right, sift, elsewhere, weigh=None) is not None
    assert MultiRelocalizer.Conf().compare_same_hypothesis

