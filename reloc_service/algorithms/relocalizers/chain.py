"""Fallback chains (``"bow+p3p,sbi+esm"``): relocalizers tried in order until one verifies."""

from __future__ import annotations

import functools
import re
from pathlib import Path

from ...core import features as feature_lib
from ...core.errors import ConfigError, NotTrainedError
from ...core.features import FeatureConf
from ...core.frame import Frame, Keyframe
from ...core.map import KeyframeMap
from ..pose.base import PoseEstimate
from ..pose.intrinsics import IntrinsicsCheck
from ..pose.intrinsics_power import estimate_underpowered
from . import overlap
from .base import Prior, Relocalizer, RelocResult, refuses_the_query
from .chain_hooks import ANSWERED, CONTENDER, ON_DOUBT, ON_VERIFIED, Contender, narrow_support
from .confirmation import (
    REFUSED,
    REFUSED_POSE,
    Refusal,
    StepEstimate,
    disagreeing_steps,
    refusal_of,
    standing_refusal,
)
from .overlap import Ahead, run_ahead


class ChainRelocalizer(Relocalizer):
    """Asks each step in turn; the first verified answer wins (its ``method`` names the step),
    with the timings of every step tried summed; a step's refusal of the query itself
    (:func:`.base.refuses_the_query`: its intrinsics disagree) ends the chain, unless a later
    step matches other features: then that step's verified pose overrules it (with
    ``confirm_intrinsics`` on that step, only where its own intrinsics test could have seen
    the error the refusal estimated: :mod:`.confirmation`), and the refusal stands where
    none verifies. Features a
    step extracts are cached on the query frame, so a later step of the same kind does not
    extract them again."""

    def __init__(self, kmap: KeyframeMap, steps: list[Relocalizer]) -> None:
        super().__init__(kmap)
        if not steps:
            raise ConfigError("chain: expected at least one relocalizer")
        self.steps = steps
        # A view that cannot check the query's intrinsics (few, coarse keypoints) leaves the
        # query to the next step, whose finer features may; only the last trusts the
        # calibration there.
        for step in steps[:-1]:
            step.defer_unchecked_intrinsics()

    @property
    def method(self) -> str:
        return ",".join(step.method for step in self.steps)

    @property
    def required_features(self) -> frozenset[str]:
        return frozenset().union(*(step.required_features for step in self.steps))

    @property
    def reads_keyframe_images(self) -> bool:
        return any(step.reads_keyframe_images for step in self.steps)

    @property
    def reads_unmapped_keypoints(self) -> bool:
        return any(step.reads_unmapped_keypoints for step in self.steps)

    def feature_confs(self) -> dict[str, FeatureConf]:
        return self.steps[0].feature_confs()

    def add_keyframe(self, keyframe: Keyframe) -> None:
        for step in self.steps:
            step.add_keyframe(keyframe)

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        for step in self.steps:
            step.remove_keyframe(keyframe)

    def train(self, *, progress: bool = False) -> None:
        for step in self.steps:
            step.train(progress=progress)

    @property
    def trained(self) -> bool:
        return all(step.trained for step in self.steps)

    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        """The first step's verified result, or NOT_RELOCALIZED with every step's reason.
        A step that is not trained yet is skipped (its reason says so). An intrinsics
        refusal answers as the class docstring says.

        A second opinion for weakly conditioned answers: when a step's pose rests on inliers
        spanning a small part of the image (:func:`.chain_hooks.narrow_support`), or on an
        intrinsics test too weak to vouch for it while a later step matches other features
        (:meth:`_underpowered`), the later steps are asked too, with that answer left on the
        query as a :class:`.chain_hooks.Contender`. The
        first later step that verifies a pose weighs the contender against its own by the
        query keypoints each explains, with its own (richer) features, and its answer is the
        chain's: the contender, its own pose, or "ambiguous". When no later step weighs it
        (none verifies anything, or one that cannot compare poses answers), the contender
        answers."""
        timings: dict[str, float] = {}
        reasons: list[str] = []
        map_version = self.map.version
        contender: Contender | None = None
        contender_step: Relocalizer = self.steps[0]
        held_underpowered = False
        refusals: list[Refusal] = []
        earlier: list[StepEstimate] = []  # the intrinsics tests of refusals and contenders
        try:
            for i, step in enumerate(self.steps):
                result = self._ask(query, i, prior, hypotheses, reasons,
                                   holding=contender is not None)
                if result is None:
                    continue
                for stage, seconds in result.timings.items():
                    timings[stage] = timings.get(stage, 0.0) + seconds
                map_version = result.map_version
                answered = query.cache.pop(ANSWERED, None)
                refused = query.cache.pop(REFUSED, None)
                refused_pose = query.cache.pop(REFUSED_POSE, None)
                if refuses_the_query(result):
                    if not self._other_features_after(i):
                        result.timings = timings
                        return result
                    refusals.append(refusal_of(result, refused))
                    _note_estimate(earlier, step, refusals[-1].check, refused_pose)
                    reasons.append(f"{step.method}: {result.reason}")
                    continue
                if contender is not None and contender.weighed:
                    # the contender weighed: the winner, or "ambiguous"
                    return _confirmed(query, step, result, answered, refusals, earlier, timings)
                if contender is not None and result.ok:
                    break  # a step that cannot weigh it does not overrule it
                if result.ok and contender is None and i + 1 < len(self.steps) \
                        and (_narrow(step, answered) or self._underpowered(i, answered)):
                    contender, contender_step = Contender(result, answered), step
                    held_underpowered = not _narrow(step, answered)
                    query.cache[CONTENDER] = contender
                    _note_estimate(earlier, step, answered.intrinsics, answered)
                    continue
                if result.ok:
                    return _confirmed(query, step, result, answered, refusals, earlier, timings)
                reasons.append(f"{step.method}: {result.reason}")
        finally:
            query.cache.pop(CONTENDER, None)
        if contender is not None and held_underpowered and getattr(
                getattr(contender_step, "conf", None), "refuse_unweighed_underpowered", False):
            return _unconfirmed(contender_step, contender.result, reasons, timings)
        if contender is not None:
            return _confirmed(query, contender_step, contender.result, contender.estimate,
                              refusals, earlier, timings)
        if refusals:  # no later step found a pose to overrule them
            refusals[0].result.timings = timings
            return refusals[0].result
        return RelocResult.failure(self.method, "; ".join(reasons), timings=timings,
                                   map_version=map_version)

    def _other_features_after(self, i: int) -> bool:
        """Whether a step after ``i`` matches other features than step ``i``: a refusal of
        the query's intrinsics (:func:`.base.refuses_the_query`) is then left to it, since
        other keypoints carry other localisation errors (ORB's pyramid-quantised corners
        bias a focal estimate that SIFT's sub-pixel ones do not); the same features would
        meet the same correspondences, and the chain answers the refusal. Features are told
        apart as the query caches them (SIFT of a reduced image is not SIFT of the image)."""
        own, own_kinds = set(self.steps[i].feature_confs()), self.steps[i].required_features
        return any(set(step.feature_confs()) - own or step.required_features - own_kinds
                   for step in self.steps[i + 1:])

    def _underpowered(self, i: int, estimate: PoseEstimate | None) -> bool:
        """Whether step ``i``'s answer, given by ``estimate``, rests on an intrinsics test too
        weak to vouch for it (:func:`..pose.intrinsics_power.estimate_underpowered`) while a
        later step matches other features, whose test may have the power (ORB's coarse
        corners let a focal error through that SIFT's keypoints reveal): that step is then
        heard too, as for a narrow support."""
        return (estimate is not None and self._other_features_after(i)
                and estimate_underpowered(estimate))

    def _ask(self, query: Frame, i: int, prior: Prior | None, hypotheses: int,
             reasons: list[str], *, holding: bool) -> RelocResult | None:
        """Step ``i``'s result, with the next step's features extracted ahead on doubt,
        or, unless the chain is ``holding`` a contender already, once the step's first
        verified pose is one the chain would hold as a contender (:meth:`_ahead_if_held`);
        None (its reason noted) when the step is not trained."""
        step = self.steps[i]
        if i + 1 < len(self.steps):
            ahead = functools.partial(extract_ahead, query, self.steps[i + 1])
            query.cache[ON_DOUBT] = ahead
            if not holding:
                query.cache[ON_VERIFIED] = functools.partial(self._ahead_if_held, i, ahead)
        try:
            return step.relocalize(query, prior=prior, hypotheses=hypotheses)
        except NotTrainedError as exc:
            reasons.append(f"{step.method}: not trained ({exc})")
            return None
        finally:
            query.cache.pop(ON_DOUBT, None)
            query.cache.pop(ON_VERIFIED, None)

    def _ahead_if_held(self, i: int, ahead: functools.partial[Ahead[None] | None],
                       estimate: PoseEstimate) -> None:
        """Run ``ahead`` (the next step's extraction) where step ``i``'s verified
        ``estimate`` is one the chain holds as a contender if the step answers it (narrow
        support, or an underpowered intrinsics test: :meth:`relocalize`), so the next step
        is asked anyway: its features are then extracted while step ``i`` hears its other
        groups. The same features as extracted later, so the answers are the same; the idle
        core is looked at first, as judging the estimate costs a little on the query's own."""
        if overlap.idle_core() and (_narrow(self.steps[i], estimate)
                                    or self._underpowered(i, estimate)):
            ahead()

    def save(self, directory: Path, *, centres: str = "float16") -> None:
        """Each step saves into its own sub-directory (``0_bow_p3p``, ...)."""
        for i, step in enumerate(self.steps):
            sub = directory / _step_dir(i, step.method)
            sub.mkdir(parents=True, exist_ok=True)
            step.save(sub, centres=centres)

    def load(self, directory: Path) -> bool:
        """Restore every step that has something saved; True if any did."""
        loaded = [step.load(directory / _step_dir(i, step.method))
                  for i, step in enumerate(self.steps)
                  if (directory / _step_dir(i, step.method)).is_dir()]
        return any(loaded)


def extract_ahead(query: Frame, step: Relocalizer) -> Ahead[None] | None:
    """Start extracting the query features ``step`` will extract (those not on ``query``
    yet, nor under way) on an idle helper thread (:func:`.overlap.run_ahead`), noting them
    on ``query`` so ``step`` waits for them rather than extracting them again. None when
    there is nothing to extract or no idle core."""
    confs = {kind: conf for kind, conf in step.feature_confs().items()
             if kind not in query.features and not query.pending_features(kind)}
    if not confs:
        return None
    image = query.image

    def extract_all() -> None:
        for kind, conf in confs.items():
            query.features[kind] = feature_lib.extract(image, conf)

    ahead = run_ahead(extract_all)
    if ahead is not None:
        for kind in confs:
            query.expect_features(kind, ahead)
    return ahead


def _confirmed(query: Frame, step: Relocalizer, result: RelocResult,
               estimate: PoseEstimate | None,
               refusals: list[Refusal], earlier: list[StepEstimate],
               timings: dict[str, float]) -> RelocResult:
    """``result`` (``step``'s answer) with the chain's ``timings``; or, where ``step``
    asks for it (its ``conf.confirm_intrinsics``) and ``result`` is a verified pose after
    earlier steps' refusals of the query's intrinsics that its own test (of ``estimate``)
    cannot overrule (:func:`.confirmation.standing_refusal`), the first such refusal; or,
    where ``step`` asks for it (``conf.compare_intrinsics``) and its estimate of the
    intrinsics disagrees with an ``earlier`` step's of the same keypoints
    (:func:`.confirmation.disagreeing_steps`; with ``conf.compare_same_hypothesis``, an
    earlier pose of another place weighed against ``result``'s on ``query`` by ``step``'s
    features instead), that refusal."""
    conf = getattr(step, "conf", None)
    if result.ok and getattr(conf, "confirm_intrinsics", False):
        result = next((r for r in (standing_refusal(refusal, result, estimate)
                                   for refusal in refusals) if r is not None), result)
    if result.ok and getattr(conf, "compare_intrinsics", False):
        weigh = getattr(step, "weigh", None)
        rivals = (functools.partial(weigh, query) if callable(weigh)
                  and getattr(conf, "compare_same_hypothesis", False) else None)
        result = disagreeing_steps(result, estimate, step.required_features, earlier,
                                   guided=getattr(conf, "compare_guided_focal", False),
                                   one_sigma=getattr(conf, "guided_focal_one_sigma", False),
                                   weigh=rivals) or result
    result.timings = timings
    return result


def _unconfirmed(step: Relocalizer, held: RelocResult, reasons: list[str],
                 timings: dict[str, float]) -> RelocResult:
    """The refusal of ``step``'s answer ``held``, a contender held for its underpowered
    intrinsics test that no later step weighed, with the later steps' ``reasons``."""
    why = (f"{step.method}: intrinsics unconfirmed: its test cannot exclude a camera that "
           f"moves the pose beyond 3 sigma, and no later step verified a pose to weigh it "
           f"against ({'; '.join(reasons) or 'none ran'})")
    return RelocResult.failure(step.method, why, inliers=held.inliers,
                               num_matches=held.num_matches,
                               reprojection_rms_px=held.reprojection_rms_px,
                               matched_keyframe_ids=held.matched_keyframe_ids,
                               timings=timings, map_version=held.map_version)


def _note_estimate(earlier: list[StepEstimate], step: Relocalizer,
                   check: IntrinsicsCheck | None, estimate: object) -> None:
    """Keep ``step``'s intrinsics test ``check`` (if any), with the pose ``estimate`` it was
    made on (None or anything else: not known), for the later steps' answers."""
    if check is not None:
        pose = estimate if isinstance(estimate, PoseEstimate) else None
        earlier.append(StepEstimate(step.method, step.required_features, check, pose))


def _narrow(step: Relocalizer, estimate: PoseEstimate | None) -> bool:
    """Whether ``step``'s answer, given by ``estimate``, rests on a small part of the image
    by ``step``'s own verification settings (False when the step does not say)."""
    conf = getattr(step, "verify_conf", None)
    return estimate is not None and conf is not None and narrow_support(estimate, conf)


def _step_dir(index: int, method: str) -> str:
    return f"{index}_{re.sub(r'[^A-Za-z0-9]+', '_', method)}"
