"""Which verified solution answers a multi relocalizer's query: the alternatives a repetition
offers, the rivals that refused the query's camera and the agreement check weighed
(:mod:`.uniqueness`), a base of :class:`.multi.MultiRelocalizer`."""

from __future__ import annotations

import abc
import functools
import time
from typing import Protocol

import numpy as np
import numpy.typing as npt

from ...core.frame import Frame
from ...core.geometry import pose_error
from ...core.map import KeyframeMap, MapState
from ..pose.base import PoseEstimate, PoseFinder
from . import uniqueness
from .base import (
    RelocResult,
    VerifyConf,
    note_map_calibration,
    plausible_first_pose,
    refuses_the_query,
    result_from_estimate,
)
from .chain_hooks import ANSWERED, CONTENDER
from .confirmation import leave_refused


class WeighingConf(Protocol):
    """The options of :class:`.multi.MultiRelocalizer.Conf` that weighing reads."""

    @property
    def unique(self) -> bool: ...
    @property
    def skip_duplicate_settle(self) -> bool: ...
    @property
    def weigh_refused_alternatives(self) -> bool: ...
    @property
    def agreement_max_distance_m(self) -> float: ...
    @property
    def agreement_max_angle_rad(self) -> float: ...


class SolutionWeighing(abc.ABC):
    """Weighs the verified candidate groups of a place+pose relocalizer against each other
    and the alternatives a repetition of the map offers: the one that answers, or why
    none does."""

    map: KeyframeMap
    pose: PoseFinder
    conf: WeighingConf
    verify_conf: VerifyConf

    @property
    @abc.abstractmethod
    def method(self) -> str:
        """The method string the results carry."""

    @property
    @abc.abstractmethod
    def require_agreement(self) -> bool:
        """Whether two independent candidate groups must verify and agree."""

    def _duplicates_a_solution(self, query: Frame, estimate: PoseEstimate | None,
                               earlier: list[PoseEstimate | None], hypotheses: int) -> bool:
        """Whether ``estimate``'s pose agrees with the first pose of a solution among the
        ``earlier`` verified estimates (:func:`.uniqueness.solutions`, as :meth:`_unique`
        forms them): with ``conf.skip_duplicate_settle`` and one hypothesis asked for, such
        an estimate cannot change the answer, so it is not verified. Verification never
        moves the pose, so its unsettled pose is the one compared."""
        if (estimate is None or not self.conf.skip_duplicate_settle or not self.conf.unique
                or hypotheses > 1 or self.require_agreement):
            return False
        verified = [e for e in earlier if e is not None]
        if not verified:
            return False
        firsts = uniqueness.solutions(verified, query.camera, self._agree,
                                      alpha=self.verify_conf.max_false_alarms)
        return any(self._agree(verified[g[0]], estimate) for g in firsts)

    def _combine(self, query: Frame, state: MapState, results: list[RelocResult],
                 estimates: list[PoseEstimate | None], timings: dict[str, float],
                 hypotheses: int) -> RelocResult:
        """The verified result that answers (the first, or with ``conf.unique`` the one that
        explains the query best, see :meth:`_unique`), with up to ``hypotheses - 1`` other
        verified ones, most confident first; or a failure naming every group's reason, the
        agreement check's or the ambiguity."""
        verified = [r for r in results if r.ok]
        if not verified and refuses_the_query(results[-1]):
            return _failure(self.method, results[-1:], timings, state.version)
        if not verified:
            return _failure(self.method, results, timings, state.version)
        contender = query.cache.get(CONTENDER) if self.conf.unique else None
        if self.require_agreement:
            refusal = self._disagreement(verified)
            if refusal:
                return RelocResult.failure(self.method, refusal, timings=timings,
                                           map_version=state.version,
                                           matched_keyframe_ids=verified[0].matched_keyframe_ids)
        best = verified[0]
        if self.conf.unique:
            start = time.perf_counter()
            verified, found, refused = self._with_alternatives(
                query, state, verified, [e for e in estimates if e is not None], hypotheses)
            if contender is not None:  # an earlier step's answer, weighed by these features
                contender.weighed = True
                if not _explains(found[0], contender.estimate, query):
                    verified.append(contender.result)
                    found.append(contender.estimate)
            chosen = (self._unique(query, state, found) if len(found) > 1
                      else uniqueness.Choice(0))
            timings["unique"] = time.perf_counter() - start
            if chosen.index is None:
                return RelocResult.failure(self.method, chosen.reason, timings=timings,
                                           map_version=state.version,
                                           matched_keyframe_ids=best.matched_keyframe_ids)
            rival = self._refusing_rival(query, state, found[chosen.index], refused)
            if rival is not None:
                rival.timings = timings
                return rival
            best = verified[chosen.index]
            query.cache[ANSWERED] = found[chosen.index]
        best.timings = timings
        others = [r for r in verified if r is not best]
        best.hypotheses = sorted(others, key=lambda r: -r.confidence)[:hypotheses - 1]
        return best

    def _with_alternatives(self, query: Frame, state: MapState, verified: list[RelocResult],
                           estimates: list[PoseEstimate], hypotheses: int
                           ) -> tuple[list[RelocResult], list[PoseEstimate],
                                      list[tuple[RelocResult, PoseEstimate]]]:
        """``verified`` and their ``estimates`` followed by the alternatives a repetition of
        the map around the first offers (:meth:`PoseFinder.alternatives`) that verify; and
        the alternatives whose intrinsics test refused the query's camera, each with its
        refusal (with ``conf.weigh_refused_alternatives``; else none). An alternative whose
        pose agrees with the first pose of a solution already among them is left unverified
        where :meth:`_duplicates_a_solution` says it cannot change the answer (verified, it
        would join that solution and never be its first; refused, its place is weighed
        already, as that solution)."""
        verified, estimates = list(verified), list(estimates)
        refused: list[tuple[RelocResult, PoseEstimate]] = []
        plausible = functools.partial(plausible_first_pose, conf=self.verify_conf)
        for alternative in self.pose.alternatives(query, estimates[0], state,
                                                  plausible=plausible):
            if self._duplicates_a_solution(query, alternative, list(estimates), hypotheses):
                continue
            note_map_calibration(alternative, query.camera, state)
            result = result_from_estimate(alternative, self.verify_conf, method=self.method,
                                          map_version=state.version, timings={})
            if result.ok:
                verified.append(result)
                estimates.append(alternative)
            elif self.conf.weigh_refused_alternatives and refuses_the_query(result):
                refused.append((result, alternative))
        return verified, estimates, refused

    def _refusing_rival(self, query: Frame, state: MapState, answer: PoseEstimate,
                        refused: list[tuple[RelocResult, PoseEstimate]]) -> RelocResult | None:
        """The refusal of the first ``refused`` alternative ``answer`` does not out-explain
        (:func:`.uniqueness.refusing_rival`), left on ``query`` for a chain; None where
        ``answer`` beats every one."""
        found = uniqueness.refusing_rival(
            answer, refused, query.camera,
            lambda est: self.pose.support(query, est.world_from_cam, state), self._agree,
            alpha=self.verify_conf.max_false_alarms)
        if found is None:
            return None
        result, alternative, why = found
        leave_refused(query, alternative)
        return RelocResult.failure(self.method, why, inliers=result.inliers,
                                   num_matches=result.num_matches,
                                   reprojection_rms_px=result.reprojection_rms_px,
                                   matched_keyframe_ids=result.matched_keyframe_ids,
                                   map_version=state.version)

    def _unique(self, query: Frame, state: MapState, estimates: list[PoseEstimate]
                ) -> uniqueness.Choice:
        """Which of the verified ``estimates`` answers (:func:`.uniqueness.decide`, by the
        query keypoints the pose finder's features show each explains)."""
        return uniqueness.decide(
            estimates, query.camera,
            lambda est: self.pose.support(query, est.world_from_cam, state), self._agree,
            alpha=self.verify_conf.max_false_alarms)

    def weigh(self, query: Frame, first: PoseEstimate, second: PoseEstimate) -> str | None:
        """None where ``first``'s pose explains significantly more of ``query``'s keypoints
        than ``second``'s, by this step's features (:func:`.uniqueness.compare` at the
        uniqueness level); else why not. Call after this step relocalized ``query``."""
        state = self.map.snapshot()
        one, two = (self.pose.support(query, e.world_from_cam, state) for e in (first, second))
        if one is None or two is None:
            return "no features to compare them by"
        c, alpha = uniqueness.compare(one, two), self.verify_conf.max_false_alarms
        if c.p_first < alpha:
            return None
        return (f"{c.only_first} vs {c.only_second} query keypoints explained by one alone, "
                f"p = {c.p_first:.2g} >= {alpha:g}")

    def _agree(self, first: PoseEstimate, second: PoseEstimate) -> bool:
        """Whether two poses agree within the agreement thresholds."""
        return not self._disagreement_of(first.world_from_cam, second.world_from_cam)

    def _disagreement(self, verified: list[RelocResult]) -> str:
        """Why two independent groups do not agree, or "" when they do."""
        if len(verified) < 2:
            return "agreement check: fewer than two candidate groups verified"
        first, second = verified[0].world_from_cam, verified[1].world_from_cam
        assert first is not None and second is not None
        refusal = self._disagreement_of(first, second)
        return f"agreement check: {refusal}" if refusal else ""

    def _disagreement_of(self, first: npt.NDArray[np.float64], second: npt.NDArray[np.float64]
                         ) -> str:
        """How two poses disagree beyond the agreement thresholds, or "" when they agree."""
        dist, angle = pose_error(first, second)
        if dist > self.conf.agreement_max_distance_m or angle > self.conf.agreement_max_angle_rad:
            return (f"independent hypotheses disagree by {dist:.2f} m and "
                    f"{np.degrees(angle):.1f} deg")
        return ""


def _explains(own: PoseEstimate, contender: PoseEstimate, query: Frame) -> bool:
    """Whether ``own`` pose reprojects most of ``contender``'s consensus within its inlier
    threshold: then the contender's evidence is explained by ``own`` too (the same solution,
    seen on less of the image), and ``own`` stands without a comparison."""
    share = uniqueness.fits_consensus(contender, own.world_from_cam, query.camera)
    return share is not None and share > 0.5


def _failure(method: str, results: list[RelocResult], timings: dict[str, float],
             map_version: int) -> RelocResult:
    """NOT_RELOCALIZED carrying the first group's evidence and every group's reason."""
    first = results[0]
    reasons = [r.reason for r in results]
    reason = reasons[0] if len(reasons) == 1 else "; ".join(
        f"group {i + 1}: {r}" for i, r in enumerate(reasons))
    return RelocResult.failure(method, reason, inliers=first.inliers,
                               num_matches=first.num_matches,
                               reprojection_rms_px=first.reprojection_rms_px,
                               matched_keyframe_ids=first.matched_keyframe_ids, timings=timings,
                               map_version=map_version)
