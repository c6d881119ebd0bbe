"""When a later chain step's pose may overrule an earlier step's refusal of the query's
intrinsics: only where its own intrinsics test could have seen the error the refusal
estimated (:mod:`..pose.intrinsics_confirmation`).

An earlier step refuses the query's camera ("intrinsics disagree": its inliers estimate a
focal the given one cannot explain); a later step, matching other features, verifies a pose
whose test passes. Either the refusal's estimate is biased (ORB's pyramid-quantised corners
bias a focal estimate) and the later pose is right, or the camera is stale and the later
test lacked the power to see it: the later pose then rests on the wrong focal. Its pass tells
them apart only where it would have refused the estimated error and its own data exclude
that error; elsewhere the refusal stands, saying which step could not confirm the camera.

Steps that match the same kind of keypoints estimate the same camera without the bias one
kind's localisation puts on another's: where the answering step's estimate disagrees with
an earlier such step's (a refusal, or a contender the chain held), the answer is refused
too (:mod:`..pose.intrinsics_agreement`), whether or not its own test passed. Only two
poses of one hypothesis can disagree about the camera: an earlier pose of another place
(another copy of a repeated picture, whose scale its focal estimate absorbed) is a rival
place instead, which the answering step weighs by the query keypoints each explains, as
:mod:`.uniqueness` weighs its own hypotheses; the answer stands only where it explains
significantly more (``compare_same_hypothesis``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ...core.frame import Frame
from ..pose.base import PoseEstimate
from ..pose.intrinsics import REFUSAL, IntrinsicsCheck
from ..pose.intrinsics_agreement import (
    disagreement_p_value,
    focal_text,
    guided_bend_p_value,
    same_hypothesis_p_value,
)
from ..pose.intrinsics_confirmation import (
    confirms,
    detection_power,
    exclusion_p_value,
    refused_theta,
)
from .base import RelocResult

#: Key of ``query.cache`` where a relocalizer that refuses the query's intrinsics leaves the
#: refusing test (:class:`..pose.intrinsics.IntrinsicsCheck`) for the chain that asked.
REFUSED = "relocalizer:refused-intrinsics"

#: Key of ``query.cache`` where that relocalizer leaves the refused pose's estimate too
#: (:class:`..pose.base.PoseEstimate`): whether a later step's pose is the same hypothesis.
REFUSED_POSE = "relocalizer:refused-pose"

#: How a refusal by :func:`disagreeing_steps` begins (an intrinsics refusal: it begins as
#: :data:`..pose.intrinsics.REFUSAL` does).
REFUSAL_BETWEEN_STEPS = "intrinsics disagree between steps"


@dataclass(frozen=True)
class Refusal:
    """A step's refusal of the query's intrinsics and the test that refused (None where the
    step did not leave it)."""

    result: RelocResult
    check: IntrinsicsCheck | None


@dataclass(frozen=True)
class StepEstimate:
    """An earlier chain step's intrinsics test of the query (``method`` the step's, matching
    landmarks of the kinds ``features``): where it refused, or where it answered a pose
    the chain held as a contender."""

    method: str
    features: frozenset[str]
    check: IntrinsicsCheck
    #: The pose that test was made on (None: not known).
    estimate: PoseEstimate | None = None


def refusal_of(result: RelocResult, check: object) -> Refusal:
    """``result``, a refusal of the query's intrinsics, with the test its step left on the
    query (``query.cache[REFUSED]``; anything else counts as none)."""
    return Refusal(result, check if isinstance(check, IntrinsicsCheck) else None)


def leave_refused(query: Frame, estimate: PoseEstimate | None) -> None:
    """Leave ``estimate``'s refusing intrinsics test on ``query`` for a chain."""
    if estimate is not None and estimate.intrinsics is not None:
        query.cache[REFUSED] = estimate.intrinsics
        query.cache[REFUSED_POSE] = estimate


def standing_refusal(refusal: Refusal, answer: RelocResult,
                     estimate: PoseEstimate | None) -> RelocResult | None:
    """``refusal``, saying ``answer``'s step cannot confirm the given camera, where
    ``answer`` (a verified pose, ``estimate`` its estimate) rests on an intrinsics test
    without the power to see the error the refusal estimated; None where it confirms the
    camera, or where the refusal left no test to judge by."""
    if refusal.check is None:
        return None
    check = None if estimate is None else estimate.intrinsics
    if check is not None and confirms(check, refusal.check):
        return None
    if check is None:
        why = "its pose was not tested against the intrinsics"
    else:
        theta = refused_theta(refusal.check)
        why = (f"its test detects that error with probability "
               f"{detection_power(check, theta):.2f} and its data reject it at "
               f"p = {exclusion_p_value(check, theta):.1e}")
    first = refusal.result
    return RelocResult.failure(
        first.method, f"{first.reason} by {first.method}; {answer.method} cannot confirm "
        f"the given intrinsics ({why})", timings=first.timings, map_version=first.map_version,
        matched_keyframe_ids=first.matched_keyframe_ids)


def disagreeing_steps(answer: RelocResult, estimate: PoseEstimate | None,
                      features: frozenset[str], earlier: list[StepEstimate], *,
                      guided: bool = False, one_sigma: bool = False,
                      weigh: Callable[[PoseEstimate, PoseEstimate], str | None] | None = None
                      ) -> RelocResult | None:
    """A refusal of ``answer`` (a verified pose, ``estimate`` its estimate, from a step
    matching landmarks of the kinds ``features``) where its intrinsics estimate disagrees
    with an ``earlier`` step's of the same kinds (:func:`..pose.intrinsics_agreement.
    disagreement_p_value`), or, with ``guided``, where guided matching bent its own focal
    estimate (:func:`..pose.intrinsics_agreement.guided_bend_p_value`, at the false-refusal
    rate; ``one_sigma``: its variant with one residual variance); None where they agree,
    or where ``answer`` was not tested.

    With ``weigh`` (None where ``answer``'s pose explains significantly more of the query
    than another's, else why not), a disagreement counts only with an earlier pose of the
    same hypothesis; one of another place (:func:`_rival`) refuses ``answer`` only where
    ``answer`` does not out-explain it. Bonferroni at the false-refusal rate over the
    earlier steps compared."""
    check = None if estimate is None else estimate.intrinsics
    if check is None:
        return None
    if guided and check.unguided is not None:
        p = guided_bend_p_value(check, one_sigma=one_sigma)
        if p < check.prior.false_refusal:
            return _refusal(answer, (
                f"{REFUSAL}: {answer.method}'s matches found without the pose estimate the "
                f"focal {focal_text(check.unguided)} off the given one, the whole set grown "
                f"around the pose {focal_text(check)} (p = {p:.1e}): guided matching bent it"))
    # A contender answering after a later step weighed it: its own step's keypoints.
    features = next((e.features for e in earlier if e.check is check), features)
    same = [e for e in earlier if e.features == features and e.check is not check]
    level = check.prior.false_refusal / max(len(same), 1)  # Bonferroni over the comparisons
    for other in same:
        p = disagreement_p_value(check, other.check)
        if p >= level:
            continue
        reason = (f"{REFUSAL_BETWEEN_STEPS}: {answer.method} estimates the focal "
                  f"{focal_text(check)} off the given one, {other.method} "
                  f"{focal_text(other.check)} (p = {p:.1e})")
        rival = None if weigh is None else _rival(estimate, other, weigh)
        if rival is None:
            return _refusal(answer, f"{reason}; one of the two poses absorbed a focal error")
        if rival:
            return _refusal(answer, f"{reason} on another place, which {answer.method}'s "
                                    f"pose does not explain the query better than ({rival})")
    return None


def _rival(estimate: PoseEstimate | None, other: StepEstimate,
           weigh: Callable[[PoseEstimate, PoseEstimate], str | None]) -> str | None:
    """Whether ``other``'s pose, whose focal estimate disagrees with the answer's
    (``estimate``), is another hypothesis that the answer does not beat: None where the two
    are one hypothesis once their focal difference is allowed for
    (:func:`..pose.intrinsics_agreement.same_hypothesis_p_value` not below the
    false-refusal rate; or either pose unknown): the disagreement is about the focal;
    otherwise a place the answer's pose explains significantly more of the query than
    (``weigh`` gives None: the other's focal absorbed its wrong place's scale) gives "",
    and one it does not, why not (``weigh``'s text)."""
    if estimate is None or other.estimate is None:
        return None
    p = same_hypothesis_p_value(estimate, other.estimate)
    if p >= other.check.prior.false_refusal:
        return None
    why = weigh(estimate, other.estimate)
    return "" if why is None else why


def _refusal(answer: RelocResult, reason: str) -> RelocResult:
    """``answer``'s step refusing the query with ``reason``."""
    return RelocResult.failure(answer.method, reason, timings=answer.timings,
                               map_version=answer.map_version,
                               matched_keyframe_ids=answer.matched_keyframe_ids)
