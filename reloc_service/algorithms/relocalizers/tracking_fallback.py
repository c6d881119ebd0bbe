"""Localization with a prior, then without: a query whose prior carries a covariance is
tracked first (:mod:`.tracking`); where tracking does not verify, the method asked
answers, with tracking's time in its timings and its reason in a refusal's."""

from __future__ import annotations

from ...core.frame import Frame
from .base import Prior, Relocalizer, RelocResult
from .tracking import TRACK

#: Tracking's stages whose names the method's own timings also use: prefixed when summed.
SHARED_STAGES = ("features", "verify", "solve")


def relocalize_with_prior(relocalizer: Relocalizer, tracker: Relocalizer | None,
                          query: Frame, *, prior: Prior | None = None,
                          hypotheses: int = 1) -> RelocResult:
    """``tracker``'s answer when ``prior`` carries a covariance and tracking verifies; else
    ``relocalizer``'s (the method asked), with tracking's time summed into its timings and
    its reason prefixed to a refusal's."""
    if (tracker is None or prior is None or prior.covariance is None
            or relocalizer.method == TRACK):
        return relocalizer.relocalize(query, prior=prior, hypotheses=hypotheses)
    tracked = tracker.relocalize(query, prior=prior, hypotheses=hypotheses)
    if tracked.ok:
        return tracked
    result = relocalizer.relocalize(query, prior=prior, hypotheses=hypotheses)
    for stage, seconds in tracked.timings.items():
        key = stage if stage not in SHARED_STAGES else f"track_{stage}"
        result.timings[key] = result.timings.get(key, 0.0) + seconds
    if not result.ok:
        result.reason = f"{TRACK}: {tracked.reason}; {result.reason}"
    return result
