"""Ferns' verified poses weighed as a multi step weighs its own
(:class:`.solution_weighing.SolutionWeighing`, with the multi relocalizer's options): the
poses ferns' RANSAC verified, followed by the alternatives a repetition of the map offers
around the first (:mod:`..pose.repetition`) that verify; the answer is the solution that
explains significantly more of the query than every other (:mod:`.uniqueness`, at the
verification's wrong-pose budget), and a repetition alternative refused for the query's
intrinsics is a rival the answer must out-explain.

A pose must be the only good explanation of the whole image. Ferns' own RANSAC hypotheses
show a repetition only where a keypoint's second class happens to be the twin landmark; a
wall of identical windows gives the twins to other keypoints, and the wrong copy then
verifies alone. The twins are found as the multi steps find them: landmarks anywhere in the
map whose descriptors the query's features match as closely as the pose's own landmarks.

Ferns' correspondences are its own keypoints classified into landmarks, without descriptors.
So the twin search starts from the query features (of the kind whose landmarks ferns
learned, extracted as the ``p3p`` pose finder extracts them) that the ferns pose explains:
its support (:mod:`..pose.support`: the local map around the pose projected into the query
and found there by guided matching), the same features every solution is compared by.
Ferns' query keypoints are SIFT's DoG extrema, detected as the SIFT extraction detects
them: ferns describes them as it detects them, and those features are that detection capped
as the extraction caps it (:func:`...core.features.capped`), not extracted a second time.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

from ...core.features import SIFT_DETECTED, capped
from ...core.frame import Features, Frame
from ...core.map import KeyframeMap, MapState
from ..pose.base import PoseEstimate
from ..pose.p3p import P3PPoseFinder
from ..pose.pnp_conf import PnPConf
from .base import RelocResult, VerifyConf
from .multi import MultiRelocalizer
from .solution_weighing import SolutionWeighing, WeighingConf


class SupportedP3P(P3PPoseFinder):
    """The ``p3p`` pose finder, whose repetition alternatives of a pose found on other
    keypoints start from the query features that pose explains."""

    def alternatives(self, query: Frame, estimate: PoseEstimate, state: MapState, *,
                     plausible: Callable[[PoseEstimate], bool] = lambda _: True
                     ) -> list[PoseEstimate]:
        """:meth:`P3PPoseFinder.alternatives` of ``estimate``'s pose, its inliers taken as
        the query features its support matches to landmarks (a pose found on ferns'
        keypoints names none of these features); none when it explains no feature."""
        explained = self.support(query, estimate.world_from_cam, state)
        if explained is None or len(explained) == 0:
            return []
        view = dataclasses.replace(estimate, inlier_keypoints=explained.keypoints,
                                   inlier_landmark_ids=explained.landmark_ids)
        return super().alternatives(query, view, state, plausible=plausible)


    def query_features(self, query: Frame, timings: dict[str, float]) -> Features:
        """:meth:`P3PPoseFinder.query_features`, taken from the SIFT detection a step left
        on ``query`` (``query.cache[SIFT_DETECTED]``: ferns' own, with descriptors) where
        there is one and the features are full-image SIFT: the same features
        (:func:`...core.features.capped`), without detecting and describing again."""
        (key, conf), = self.feature_confs().items()
        detection = query.cache.get(SIFT_DETECTED)
        if detection is None or conf.kind != "sift" or conf.scale != 1:
            return super().query_features(query, timings)
        start = time.perf_counter()
        feats = query.features_of(key, lambda: capped(query.image, detection, conf))
        timings["features"] = time.perf_counter() - start
        return feats


def supported_p3p(kind: str, pnp_conf: PnPConf) -> SupportedP3P:
    """The pose finder ferns weighs its poses with: ``p3p`` on features of ``kind`` (its
    other options at their defaults), solving with ferns' RANSAC settings ``pnp_conf``."""
    fields = {f.name: getattr(pnp_conf, f.name) for f in dataclasses.fields(PnPConf)}
    return SupportedP3P(P3PPoseFinder.Conf(kind=kind, **fields))


class FernsWeighing(SolutionWeighing):
    """Which of ferns' verified poses answers, weighed with the repetition alternatives a
    multi step weighs (module docstring)."""

    def __init__(self, kmap: KeyframeMap, pose: SupportedP3P, verify_conf: VerifyConf,
                 conf: WeighingConf | None = None) -> None:
        self.map = kmap
        self.pose = pose
        self.verify_conf = verify_conf
        self.conf = conf if conf is not None else MultiRelocalizer.Conf()

    @property
    def method(self) -> str:
        return "ferns"

    @property
    def require_agreement(self) -> bool:
        return False

    def answer(self, query: Frame, state: MapState, results: list[RelocResult],
               estimates: list[PoseEstimate | None], timings: dict[str, float],
               hypotheses: int) -> RelocResult:
        """The result that answers among ``results`` (``estimates``: each verified one's
        estimate, None for the others), with up to ``hypotheses - 1`` other verified ones;
        or a failure saying why none does. The first result when none verified."""
        if not any(r.ok for r in results):
            return results[0]
        spent: dict[str, float] = {}
        self.pose.query_features(query, spent)  # the features supports and twins compare
        timings["weigh_features"] = spent.get("features", 0.0)
        return self._combine(query, state, results, estimates, timings, hypotheses)
