"""The multi relocalizer (thesis chapter 4, MultipleRelocalizer): a place finder proposes
keyframes, a pose finder turns them into a pose, the shared verification judges it."""

from __future__ import annotations

import dataclasses
import time
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...core.errors import ConfigError, NotTrainedError, StorageError
from ...core.features import FeatureConf
from ...core.frame import Frame, Keyframe
from ...core.landmark_rows import check_every_row
from ...core.map import KeyframeMap, MapState
from ...core.methods import MethodStep
from ...core.plugins import make_conf
from ..place.base import PlaceCandidate, PlaceFinder, create_place_finder
from ..pose.base import POSE_FINDERS, PoseEstimate, PoseFinder, create_pose_finder
from .base import (
    Prior,
    Relocalizer,
    RelocResult,
    VerifyConf,
    note_map_calibration,
    plausible_first_pose,
    refuses_the_query,
    register,
    result_from_estimate,
)
from .chain_hooks import doubt, first_verified
from .confirmation import leave_refused
from .overlap import run_beside
from .solution_weighing import SolutionWeighing

#: Suffix of a place finder's saved model: its msgpack state, zlib-compressed.
PACKED_MODEL = ".msgpack.zlib"


@register("multi")
class MultiRelocalizer(SolutionWeighing, Relocalizer):
    """``"<place>+<pose>"``: candidates from the place finder, split into groups (one keyframe
    per group, or ``num_candidates`` pooled keyframes for pose finders that pool, like p3p),
    each group answered by the pose finder and verified, best group first."""

    @dataclass(frozen=True)
    class Conf:
        #: Keyframes pooled into one group for pose finders that pool candidates (p3p).
        num_candidates: int = 5
        #: Groups tried, in place-finder order, until one verifies (1 = thesis behaviour).
        max_groups: int = 3
        #: Accept only when two independent candidate groups verify and agree; None: only for
        #: pose finders whose evidence is photometric (``PoseFinder.needs_agreement``).
        require_agreement: bool | None = None
        agreement_max_distance_m: float = 0.25
        agreement_max_angle_rad: float = 0.087
        #: Extract the query's features for the pose finder on an idle helper thread while
        #: the place finder ranks keyframes (OpenCV releases the GIL, so a query uses a second
        #: core when one is free: :mod:`.overlap`). Answers are the same either way; off, the
        #: pose finder extracts them after the place finder, on the query's thread.
        overlap: bool = True
        #: When a candidate group fails to verify and more remain, let a fallback chain
        #: start its next step's feature extraction on an idle helper thread
        #: (:func:`.chain_hooks.doubt`): where this step fails altogether, the next one finds its
        #: features extracted or under way. Answers are the same either way; work done
        #: ahead for nothing (a later group verifies) only ever uses an idle core. Likewise
        #: at the first verified group, where the chain will hold that pose as a contender
        #: and ask its next step too (:func:`.chain_hooks.first_verified`).
        look_ahead: bool = True
        #: Hear every candidate group (up to ``max_groups``) even after one verified, and
        #: answer only a pose that explains the query significantly better than every other
        #: verified pose (:mod:`.uniqueness`): a repeated picture, a periodic wall or an
        #: identical object elsewhere verifies as well as the true pose does. Off: the first
        #: verified group answers (faster, and wrong wherever the scene repeats).
        unique: bool = True
        #: In a fallback chain, let this step's verified pose overrule an earlier step's
        #: refusal of the query's intrinsics only where its own intrinsics test could have
        #: seen the error the refusal estimated and its data exclude that error
        #: (:mod:`.confirmation`); elsewhere the refusal stands. Off: any verified pose of a
        #: step with other features overrules it (a stale focal's pose too, where an
        #: earlier step saw the error and the later one could not).
        confirm_intrinsics: bool = True
        #: In a fallback chain, refuse this step's verified pose where its intrinsics
        #: estimate disagrees with an earlier step's that matched the same kind of keypoints
        #: (one that refused the query's intrinsics, or answered a pose the chain held as a
        #: contender): a two-sample test at the intrinsics test's false-refusal rate
        #: (:mod:`..pose.intrinsics_agreement`). Off: each step's test alone judges it.
        compare_intrinsics: bool = True
        #: With ``compare_intrinsics``, count a disagreement only with an earlier pose of
        #: the same hypothesis once the focal difference is allowed for (chi-square at the
        #: intrinsics test's false-refusal rate); a pose of another place is weighed as a
        #: rival instead: this step's pose answers only where it explains significantly
        #: more of the query (:mod:`.confirmation`). Off: every earlier pose is compared.
        compare_same_hypothesis: bool = True
        #: With ``compare_intrinsics``, also refuse this step's pose where guided matching
        #: bent its focal estimate: its unguided matches' estimate disagrees with its whole
        #: set's (Hausman's test of the focal at the false-refusal rate,
        #: :func:`..pose.intrinsics_agreement.guided_bend_p_value`). Off: with the right
        #: camera it refused two correct poses of about 400 (room-hard query 33,
        #: repeated-hard query 30), more than its level predicts.
        compare_guided_focal: bool = False
        #: With ``compare_guided_focal``, take both focal variances of that test from one
        #: residual variance, the unguided matches' (Hausman's test under its null: guided
        #: matches fitting a wrong focal inflate the whole set's own variance until the test
        #: sees nothing; :func:`..pose.intrinsics_agreement.guided_bend_p_value`). Off: each
        #: set's own (docs/focal_census.md): with a focal 15 % long it refuses repeated-hard
        #: query 50 (32 cm, 7.2 sigma), but with the right camera the chain loses
        #: repeated-hard query 30 (5 cm: its 19 unguided matches estimate -27 +- 7 %).
        guided_focal_one_sigma: bool = False
        #: With ``unique``, leave unverified a candidate group, or an alternative a
        #: repetition offers, whose pose agrees (within the agreement thresholds) with the
        #: first pose of a solution verified earlier on the query: verified or not, it would
        #: join that solution and never be its first, which is all
        #: :func:`.uniqueness.decide` answers with, so the answer is the same and its
        #: intrinsics test is saved. Applies only where one hypothesis is asked for and no
        #: agreement is required (both read every verified group).
        skip_duplicate_settle: bool = True
        #: With ``skip_duplicate_settle``, set a candidate group heard after one verified
        #: aside at its first pose that agrees with the first pose of a verified solution
        #: (its first pool's, or its group's before guided matching) and is itself a first
        #: consensus chance would not produce, without matching the whole group or growing
        #: that pose: on 7scenes_redkitchen most groups heard for the uniqueness check end
        #: so (their share of the ORB step's time halves). Not answer-identical in
        #: principle: the full pose is not computed, and can move a few centimetres across
        #: the agreement thresholds (2 of 92 such groups on a fresh room-hard render, no
        #: answer changed in 1253 queries; docs/step_census.md). Off: every group's pose is
        #: found in full, then compared.
        duplicates_early: bool = True
        #: With ``unique``, weigh the repetition alternatives whose intrinsics test refused
        #: the query's camera as rivals of the answer: the answer stands only where it
        #: explains significantly more of the query than each (:func:`.uniqueness.compare`
        #: at the verification's wrong-pose budget); else the query is refused with that
        #: alternative's intrinsics refusal. An alternative the answer does not out-explain
        #: is as likely the true place, and there the query's camera disagrees with the
        #: correspondences. Off: a refused alternative is dropped like any unverified one
        #: (with the right camera no answer of the 18 evaluation sets changes: the 2
        #: refused alternatives met were out-explained; room-hard with a focal 15 % long:
        #: query 8's 98 cm / 139 deg pose is refused).
        weigh_refused_alternatives: bool = True
        #: In a fallback chain, refuse this step's pose where the chain held it as a
        #: contender for its underpowered intrinsics test (the data cannot exclude a camera
        #: that moves it beyond 3 sigma: :func:`..pose.intrinsics_power.estimate_underpowered`)
        #: and no later step verified a pose to weigh it against: nothing then vouches for
        #: the given camera. Off: the contender answers.
        refuse_unweighed_underpowered: bool = False

        def __post_init__(self) -> None:
            if self.num_candidates < 1 or self.max_groups < 1:
                raise ConfigError(f"multi: num_candidates and max_groups must be >= 1, got "
                                  f"{self.num_candidates}, {self.max_groups}")
            if self.agreement_max_distance_m <= 0 or self.agreement_max_angle_rad <= 0:
                raise ConfigError("multi: agreement thresholds must be positive")

    def __init__(self, kmap: KeyframeMap, place: PlaceFinder, pose: PoseFinder, *,
                 conf: MultiRelocalizer.Conf | None = None, verify_conf: VerifyConf | None = None,
                 pose_label: str | None = None) -> None:
        super().__init__(kmap)
        self.place = place
        self.pose = pose
        self.conf: MultiRelocalizer.Conf = conf or MultiRelocalizer.Conf()
        self.verify_conf = verify_conf or VerifyConf()
        #: The pose part of the method string (``"p3p"`` or ``"p3p:orb"``).
        self.pose_label = pose_label or pose.name

    @classmethod
    def from_options(cls, step: MethodStep, kmap: KeyframeMap,
                     options: Mapping[str, Mapping[str, Any]]) -> MultiRelocalizer:
        """Build the step ``"<place>+<pose>"`` or ``"<place>+<pose>:<features>"``;
        ``options[name]`` configures each part, ``"multi"`` this class and ``"verify"`` the
        verification.

        The ``:<features>`` suffix (``"sbi+p3p:orb"``) runs the pose finder on that feature
        kind with the kind's own default count (:data:`STEP_FEATURES`), whatever
        ``options[pose]`` says about ``kind`` and ``max_features``: so one chain can hold an
        ORB step and a SIFT step. ``options["<pose>:<features>"]`` (e.g. ``"p3p:orb"``)
        configures that variant further, over ``options[pose]``."""
        if step.place is None:  # a relocalizer named alone: 'multi'
            raise ConfigError(f"multi relocalizer: expected '<place>+<pose>' or "
                              f"'<place>+<pose>:<features>' (e.g. 'sbi+p3p', 'sbi+p3p:orb'), "
                              f"got {str(step)!r}")
        place = create_place_finder({**options.get(step.place, {}), "name": step.place}, kmap)
        pose = create_pose_finder(pose_options(step, options))
        conf = make_conf(cls.Conf, options.get("multi"), owner="relocalizer multi")
        verify_conf = make_conf(VerifyConf, options.get("verify"), owner="verify")
        return cls(kmap, place, pose, conf=conf, verify_conf=verify_conf,
                   pose_label=step.pose_label)

    @property
    def method(self) -> str:
        return f"{self.place.name}+{self.pose_label}"

    @property
    def required_features(self) -> frozenset[str]:
        return frozenset(self.place.required_features) | frozenset(self.pose.required_features)

    @property
    def reads_keyframe_images(self) -> bool:
        return self.place.reads_keyframe_images or self.pose.reads_keyframe_images

    @property
    def reads_unmapped_keypoints(self) -> bool:
        return self.pose.reads_unmapped_keypoints

    def feature_confs(self) -> dict[str, FeatureConf]:
        """The pose finder's, and the place finder's (which extracts first where both
        extract one kind: bow+p3p)."""
        return {**self.pose.feature_confs(), **self.place.feature_confs()}

    @property
    def group_size(self) -> int:
        """Keyframes per candidate group handed to the pose finder."""
        return self.conf.num_candidates if self.pose.pools_candidates else 1

    @property
    def require_agreement(self) -> bool:
        """Configured, or implied by a photometric pose finder (see ``needs_agreement``)."""
        if self.conf.require_agreement is None:
            return self.pose.needs_agreement
        return self.conf.require_agreement

    def add_keyframe(self, keyframe: Keyframe) -> None:
        if self.reads_unmapped_keypoints:
            check_every_row(keyframe, f"{self.method}'s {self.pose.name} matching")
        self.place.add_keyframe(keyframe)

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        self.place.remove_keyframe(keyframe)

    def train(self, *, progress: bool = False) -> None:
        self.place.train()
        self.pose.prepare_map(self.map.snapshot())

    @property
    def trained(self) -> bool:
        return self.place.trained

    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        """Place candidates -> groups -> pose -> verification; the first verified group
        answers, with up to ``hypotheses - 1`` further verified groups in ``hypotheses``."""
        if not self.place.trained:
            raise NotTrainedError(f"{self.method}: the {self.place.name} place finder needs "
                                  "train()")
        state = self.map.snapshot()
        timings: dict[str, float] = {}
        allowed = _allowed_ids(state, prior)
        groups = None
        if self._overlaps(query):
            groups = self._groups_beside_features(query, state, allowed, max(1, hypotheses),
                                                  timings)
        if groups is None:  # the place finder, then the pose finder, on this thread
            start = time.perf_counter()
            groups = self._candidate_groups(query, state, allowed, max(1, hypotheses))
            timings["place"] = time.perf_counter() - start
        if not groups:
            return RelocResult.failure(self.method, _no_candidate_reason(state, allowed),
                                       timings=timings, map_version=state.version)
        results, estimates = self._answer_groups(query, groups, state, timings,
                                                 max(1, hypotheses))
        return self._combine(query, state, results, estimates, timings, max(1, hypotheses))

    def _overlaps(self, query: Frame) -> bool:
        """Whether the place finder runs beside the pose finder's feature extraction: with
        ``conf.overlap``, when the pose finder has features to extract that the place finder
        does not extract itself (two threads would each extract them)."""
        if not self.conf.overlap:
            return False
        kinds = self.pose.query_kinds(query)
        return bool(kinds) and not kinds & self.place.required_features

    def _groups_beside_features(self, query: Frame, state: MapState, allowed: set[int] | None,
                                hypotheses: int, timings: dict[str, float]
                                ) -> list[list[PlaceCandidate]] | None:
        """:meth:`_candidate_groups`, then :meth:`PoseFinder.prepare_candidates` of the first
        group, on a helper thread (:mod:`.overlap`) while this thread extracts the query's
        features (:meth:`PoseFinder.prepare_query`, cached on the query). The place
        finder's error is raised here; work done ahead that fails is left to
        :meth:`PoseFinder.find_pose`, which meets the same error where it needs that work,
        as it would without the overlap. None, having done nothing, when no helper runs
        (no idle core: see :func:`.overlap.run_beside`)."""
        query.image  # noqa: B018 (decoded here, once, before two threads read the pixels)

        def place() -> tuple[list[list[PlaceCandidate]], dict[str, float]]:
            start = time.perf_counter()
            groups = self._candidate_groups(query, state, allowed, hypotheses)
            spent = {"place": time.perf_counter() - start}
            if groups:
                try:
                    spent.update(self.pose.prepare_candidates(query, groups[0], state))
                except Exception:  # noqa: BLE001, S110 (met again by find_pose, see above)
                    pass
            return groups, spent

        beside = run_beside(place)
        if not beside.overlapped:
            return None
        try:
            _add_timings(timings, self.pose.prepare_query(query))
        except Exception:  # noqa: BLE001, S110 (met again by find_pose, see above)
            pass
        finally:
            waited = time.perf_counter()
            groups, spent = beside.result()
        timings["overlap_wait"] = time.perf_counter() - waited  # beyond the extraction
        _add_timings(timings, spent)
        return groups

    def _candidate_groups(self, query: Frame, state: MapState, allowed: set[int] | None,
                          hypotheses: int) -> list[list[PlaceCandidate]]:
        """Candidates (still in ``state``) split into consecutive groups, best first."""
        if allowed is not None and not allowed:
            return []
        n_groups = max(self.conf.max_groups, hypotheses, 2 if self.require_agreement else 1)
        size = self.group_size
        found = self.place.find_places(query, size * n_groups, allowed=allowed)
        found = [c for c in found if c.keyframe_id in state.keyframes]
        return [found[i:i + size] for i in range(0, len(found), size)]

    def _answer_groups(self, query: Frame, groups: list[list[PlaceCandidate]], state: MapState,
                       timings: dict[str, float], hypotheses: int
                       ) -> tuple[list[RelocResult], list[PoseEstimate | None]]:
        """Pose and verify group after group, until enough have verified (every group with
        ``conf.unique``) or, before any has, one refuses the query itself
        (:func:`.base.refuses_the_query`: after a verified pose whose intrinsics passed, a
        later group's disagreeing ones are more likely a wrong pose's); every result, and
        the estimate of each verified one (None for the others)."""
        wanted = max(hypotheses, 2 if self.require_agreement else 1)
        results: list[RelocResult] = []
        estimates: list[PoseEstimate | None] = []
        for group in groups:
            # Settled by the verification, only past the tests that do not read the
            # intrinsics test (most groups that fail, fail those).
            known = self._known_solution(query, estimates, hypotheses)
            estimate = (self.pose.find_pose_deferred(query, group, state) if known is None else
                        self.pose.find_pose_deferred(query, group, state, known=known))
            if self._duplicates_a_solution(query, estimate, estimates, hypotheses):
                assert estimate is not None
                _add_timings(timings, estimate.timings)  # its pose was found all the same
                continue
            note_map_calibration(estimate, query.camera, state)
            settled = 0.0 if estimate is None else estimate.timings.get("settle", 0.0)
            start = time.perf_counter()
            result = result_from_estimate(estimate, self.verify_conf, method=self.method,
                                          map_version=state.version, timings={})
            verified = time.perf_counter() - start
            if estimate is not None:  # the settling verification ran is its own stage
                verified -= estimate.timings.get("settle", 0.0) - settled
                _add_timings(timings, estimate.timings)
            _add_timings(timings, {"verify": verified})
            results.append(result)
            estimates.append(estimate if result.ok else None)
            if refuses_the_query(result) and not any(r.ok for r in results):
                leave_refused(query, estimate)  # for a chain: the test that refused
                break  # the query's camera: every other group would meet it too
            if (self.conf.look_ahead and not result.ok and len(results) < len(groups)
                    and not any(r.ok for r in results)):
                doubt(query)
            if self.conf.look_ahead and result.ok and sum(r.ok for r in results) == 1:
                first_verified(query, estimate)
            if sum(r.ok for r in results) >= wanted and not self.conf.unique:
                break
        return results, estimates

    def _known_solution(self, query: Frame, estimates: list[PoseEstimate | None],
                        hypotheses: int) -> Callable[[PoseEstimate], bool] | None:
        """With ``conf.duplicates_early`` and a group verified, the test
        :meth:`_duplicates_a_solution` applies to a group's pose, for the pose finder to stop
        at the first pose it passes; None otherwise. Only a pose that is itself a first
        consensus chance would not produce (:func:`.base.plausible_first_pose`) can pass: a
        pose of a few inliers agrees with a verified one by chance as easily as not, and the
        group's full pose may then lie elsewhere."""
        if not self.conf.duplicates_early or not any(e is not None for e in estimates):
            return None
        return lambda est: (plausible_first_pose(est, self.verify_conf)
                            and self._duplicates_a_solution(query, est, estimates, hypotheses))

    def defer_unchecked_intrinsics(self) -> None:
        self.verify_conf = dataclasses.replace(self.verify_conf,
                                               trust_unchecked_intrinsics=False)

    def save(self, directory: Path, *, centres: str = "float16") -> None:
        """Write the place finder's trained model (if any) as ``place_<name>.msgpack.zlib``:
        zlib keeps about two thirds of a vocabulary tree and its inverted file (word counts
        and sorted word ids repeat), exactly."""
        state = self.place.state(centres=centres)
        if state is not None:
            import msgpack  # only needed when a place finder has a model to persist

            (directory / f"place_{self.place.name}{PACKED_MODEL}").write_bytes(
                zlib.compress(msgpack.packb(state, use_bin_type=True), 6))

    def load(self, directory: Path) -> bool:
        """Restore what :meth:`save` wrote (or an older save's plain ``.msgpack``); False if
        there is nothing for this place finder."""
        packed = directory / f"place_{self.place.name}{PACKED_MODEL}"
        path = packed if packed.is_file() else directory / f"place_{self.place.name}.msgpack"
        if not path.is_file():
            return False
        import msgpack

        data = path.read_bytes()
        if path == packed:
            try:
                data = zlib.decompress(data)
            except zlib.error as exc:
                raise StorageError(f"{path}: expected the zlib of a msgpack model ({exc})"
                                   ) from exc
        self.place.load_state(msgpack.unpackb(data, raw=False, strict_map_key=False))
        return True


#: What a ``:<kind>`` suffix sets in the pose finder's options (the keys its ``Conf`` has):
#: the feature kind and its count per query (ORB's 500 are the fast path, ORB-SLAM's budget
#: at 640x480; SIFT's 2000 the pose finder's default) and, for ORB, matching the best
#: candidate's landmarks before the whole group's (``first_pool_keyframes``), as the fast
#: path spends its time in matching otherwise.
STEP_FEATURES: dict[str, dict[str, Any]] = {
    "orb": {"kind": "orb", "max_features": 500, "first_pool_keyframes": 1},
    "sift": {"kind": "sift", "max_features": 2000},
    # SIFT of the query reduced to half size (a quarter of the pixels): where blur or
    # distance has removed the finest scales, its keypoints are the coarse ones full-size
    # SIFT finds too, at about a quarter of the cost; matched to the map's SIFT landmarks.
    "sift-half": {"kind": "sift", "max_features": 1000, "query_scale": 0.5,
                  "first_pool_keyframes": 1}}


def pose_options(step: MethodStep, options: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The options dict (``name`` included) of the step's pose finder, ``"p3p"`` or, with a
    feature kind, ``"p3p:orb"``."""
    name, kind = step.pose, step.features
    assert name is not None, "a place+pose step"
    if kind is None:
        return {**options.get(name, {}), "name": name}
    if kind not in STEP_FEATURES:
        raise ConfigError(f"multi relocalizer: expected '<pose>:<features>' with features one "
                          f"of {sorted(STEP_FEATURES)} (e.g. 'p3p:orb'), got {step.pose_label!r}")
    fields = {f.name for f in dataclasses.fields(POSE_FINDERS.lookup(name).Conf)}
    preset = {k: v for k, v in STEP_FEATURES[kind].items() if k in fields}
    if "kind" not in preset:
        raise ConfigError(f"multi relocalizer: pose finder {name!r} takes no features, so "
                          f"{step.pose_label!r} means nothing; expected e.g. 'p3p:orb'")
    if "query_scale" in STEP_FEATURES[kind] and "query_scale" not in preset:
        raise ConfigError(f"multi relocalizer: pose finder {name!r} does not reduce the query "
                          f"image, so {step.pose_label!r} means nothing; expected e.g. "
                          f"'p3p:{kind}'")
    return {**options.get(name, {}), **preset, **options.get(f"{name}:{kind}", {}),
            "name": name}


def _allowed_ids(state: MapState, prior: Prior | None) -> set[int] | None:
    """Keyframe ids whose centre lies within the prior's radius; None without a prior or
    without a radius (a prior with a covariance alone restricts nothing)."""
    if prior is None or prior.radius_m is None:
        return None
    ids = np.array(state.keyframe_ids(), np.int64)
    if len(ids) == 0:
        return set()
    dist = np.linalg.norm(state.positions_world(ids.tolist()) - prior.world_from_cam[:3, 3], axis=1)
    return set(ids[dist <= prior.radius_m].tolist())


def _no_candidate_reason(state: MapState, allowed: set[int] | None) -> str:
    if not state.keyframes:
        return "the map has no keyframe"
    if allowed is not None and not allowed:
        return "no keyframe within the prior's radius"
    return "the place finder proposed no keyframe"


def _add_timings(total: dict[str, float], more: Mapping[str, float]) -> None:
    """Sum ``more`` into ``total`` stage by stage (in place)."""
    for stage, seconds in more.items():
        total[stage] = total.get(stage, 0.0) + seconds
