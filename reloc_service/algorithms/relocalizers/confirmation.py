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
"""

from __future__ import annotations

from dataclasses import dataclass

from ...core.frame import Frame
from ..pose.base import PoseEstimate
from ..pose.intrinsics import IntrinsicsCheck
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


@dataclass(frozen=True)
class Refusal:
    """A step's refusal of the query's intrinsics and the test that refused (None where the
    step did not leave it)."""

    result: RelocResult
    check: IntrinsicsCheck | None


def refusal_of(result: RelocResult, check: object) -> Refusal:
    """``result``, a refusal of the query's intrinsics, with the test its step left on the
    query (``query.cache[REFUSED]``; anything else counts as none)."""
    return Refusal(result, check if isinstance(check, IntrinsicsCheck) else None)


def leave_refused(query: Frame, estimate: PoseEstimate | None) -> None:
    """Leave ``estimate``'s refusing intrinsics test on ``query`` for a chain."""
    if estimate is not None and estimate.intrinsics is not None:
        query.cache[REFUSED] = estimate.intrinsics


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
