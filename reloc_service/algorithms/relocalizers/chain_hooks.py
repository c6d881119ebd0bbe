"""What a fallback chain and its steps leave each other in ``query.cache`` while one query
runs: the hooks a chain leaves a step (start the next step's work early on an idle core), the
pose a step answered, and an earlier step's answer for a later step to weigh against its own.

The chain (:mod:`.chain`) and the steps it runs (:mod:`.multi`, :mod:`.solution_weighing`,
:mod:`.tracking`) share these keys and no other state: a step run outside a chain finds no
hook and leaves its answer unread.
"""

from __future__ import annotations

from dataclasses import dataclass

from reloc_client.result import RelocResult

from ...core.frame import Frame
from ..pose.base import PoseEstimate
from .base import VerifyConf
from .inlier_coverage import inlier_spread

#: ``query.cache`` key of a callable a fallback chain leaves to the step it runs: the step
#: calls it (once, through :func:`doubt`) when it first has reason to expect it may not
#: verify, so the chain can start the next step's work on an idle core meanwhile.
ON_DOUBT = "relocalizer:on-doubt"
#: ``query.cache`` key of a callable a fallback chain leaves to the step it runs, taking a
#: :class:`PoseEstimate`: the step calls it (once, through :func:`first_verified`) with its
#: first verified pose, so the chain can start the next step's work on an idle core where
#: that pose is one it will hold as a contender and ask the next step about anyway.
ON_VERIFIED = "relocalizer:on-verified"


#: Key of ``query.cache`` where a relocalizer that verified a pose leaves that pose's
#: :class:`PoseEstimate` for the chain that asked (:data:`CONTENDER`).
ANSWERED = "relocalizer:answered"
#: Key of ``query.cache`` where a fallback chain leaves an earlier step's answer, as
#: ``Contender``, for a later step to weigh against its own poses. A step that weighs it
#: sets ``Contender.weighed``.
CONTENDER = "relocalizer:contender"


@dataclass
class Contender:
    """An earlier step's verified answer that a later step should compare with its own:
    the answer, its estimate, and whether a step has weighed it yet."""

    result: RelocResult
    estimate: PoseEstimate
    weighed: bool = False


def narrow_support(estimate: PoseEstimate, conf: VerifyConf) -> bool:
    """Whether ``estimate``'s inliers span less of the image than the coverage test asks of
    a planar patch (``min_inlier_cells / coverage_grid**2``): a pose fixed by one small area
    is weakly conditioned (a rotation about that area trades against a translation), so a
    few wrong matches from a repeated texture can move it far, and a step that sees more of
    the image should be heard too."""
    spread = inlier_spread(estimate)
    return spread is not None and spread < conf.min_inlier_cells / conf.coverage_grid**2


def doubt(query: Frame) -> None:
    """Call the hook a chain left on ``query`` (:data:`ON_DOUBT`), if any, and drop it."""
    hook = query.cache.pop(ON_DOUBT, None)
    if hook is not None:
        hook()


def first_verified(query: Frame, estimate: PoseEstimate | None) -> None:
    """Call the hook a chain left on ``query`` (:data:`ON_VERIFIED`), if any, with the
    step's first verified ``estimate``, and drop it."""
    hook = query.cache.pop(ON_VERIFIED, None)
    if hook is not None and estimate is not None:
        hook(estimate)
