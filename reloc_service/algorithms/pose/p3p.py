"""P3P pose finder (thesis 3.1.3, improved): query features matched to the landmarks of the
top candidate keyframes, then the pose by :mod:`.pnp` (P3P in LO-RANSAC, refined through the
real camera model, with the reprojection RMS and a 6x6 covariance as evidence for
verification)."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from ...core import features as feature_lib
from ...core.cameras import Camera
from ...core.errors import ConfigError
from ...core.frame import Features, Frame, Keyframe
from ...core.map import MapState
from ..place.base import PlaceCandidate
from .base import PoseEstimate, PoseFinder, Support, register
from .guided import GuidedConf, search_by_projection
from .intrinsics_guided import unguided_positions, with_unguided_test
from .landmark_matches import best_per_landmark, union_matches
from .landmark_pool import LandmarkPool
from .map_consistency import prepare_map, settle_pose_errors
from .map_pool import map_pool
from .pnp import level_scales, solve_pnp_indexed
from .pnp_conf import PnPConf
from .point_uncertainty import PointUncertainty
from .repetition import (
    RepetitionConf,
    alternative_poses,
    twin_correspondences,
    unexplained_matches,
)
from .repetition_index import IndexConf, RepetitionIndex
from .support import explained_keypoints

Array = npt.NDArray[np.float64]


@register("p3p")
class P3PPoseFinder(PoseFinder):
    """Matches query features (SIFT, or ORB as the fast path) to the landmarks seen by all the
    candidate keyframes at once, then :func:`.pnp.solve_pnp`."""

    #: The multi relocalizer gives this pose finder a whole group of candidates (pooled).
    pools_candidates: ClassVar[bool] = True

    @dataclass(frozen=True)
    class Conf(PnPConf):
        kind: str = "sift"
        max_features: int = 2000
        #: Lowe's ratio (thesis 3.1.3).
        ratio: float = 0.8
        #: Grow a first pose by guided matching (search by projection, :mod:`.guided`) over
        #: the landmarks of the candidates and of the keyframes near that pose, then re-solve.
        guided: bool = True
        #: ... when the first pose has fewer inliers than this (ORB-SLAM's relocalization
        #: searches by projection below 50 inliers; above, the pose stands on its own).
        guided_below_inliers: int = 50
        #: Keyframes near the first pose whose landmarks guided matching projects.
        guided_keyframes: int = 10
        #: Match first against the landmarks of only this many best candidates (None: all of
        #: the group at once); when that pose has fewer than ``guided_below_inliers``
        #: inliers, or none, the whole group's landmarks are matched as without this. A query
        #: that resembles its best keyframe then pays for one keyframe's landmarks, not five.
        first_pool_keyframes: int | None = None
        #: Weigh each keypoint by its pyramid level: its localisation noise is
        #: ``keypoint_sigma_px * factor^level`` (``factor`` the detector's scale step between
        #: levels). Off keeps every keypoint at ``keypoint_sigma_px``.
        level_sigmas: bool = False
        #: Extract the query's features on its image reduced by this factor
        #: (:class:`~reloc_service.core.features.FeatureConf` ``scale``); each keypoint is then
        #: located to ``1 / query_scale`` full-image pixels, which its weight carries.
        query_scale: float = 1.0
        #: Spread the query's keypoints over a ``query_grid`` x ``query_grid`` partition of
        #: the image (ORB only; :func:`~reloc_service.core.features.spread_over_grid`); 1
        #: keeps the strongest wherever they are.
        query_grid: int = 1
        #: The repetition check's whole-map pool is scanned in full up to this many landmarks,
        #: searched in an index above (:class:`~.repetition_index.IndexConf` ``exact_rows``).
        repetition_exact_rows: int = IndexConf.exact_rows

        def __post_init__(self) -> None:
            super().__post_init__()
            feature_lib.FeatureConf(kind=self.kind, max_features=self.max_features,
                                    scale=self.query_scale, grid=self.query_grid)
            if not 0 < self.ratio <= 1:
                raise ConfigError(f"p3p: ratio must be in (0, 1], got {self.ratio}")
            if self.first_pool_keyframes is not None and self.first_pool_keyframes < 1:
                raise ConfigError(f"p3p: first_pool_keyframes must be >= 1 or None, got "
                                  f"{self.first_pool_keyframes}")
            if self.repetition_exact_rows < 0:
                raise ConfigError(f"p3p: repetition_exact_rows must be >= 0, got "
                                  f"{self.repetition_exact_rows}")

        def repetition_index(self) -> IndexConf:
            """How the repetition check's whole-map pool is indexed."""
            return IndexConf(exact_rows=self.repetition_exact_rows)

    def __init__(self, conf: P3PPoseFinder.Conf) -> None:
        super().__init__(conf)
        self.required_features = frozenset({conf.kind})

    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        """Pose from the landmarks of all ``candidates`` still in ``state``; None if none is.

        When too few matches survive for a pose, the estimate is the best keyframe's pose with
        zero inliers, so the verification refuses it with the counts as the reason."""
        found = self.find_pose_deferred(query, candidates, state)
        if found is not None:
            found.settle()
        return found

    def find_pose_deferred(self, query: Frame, candidates: list[PlaceCandidate],
                           state: MapState, *, known: Callable[[PoseEstimate], bool] | None = None
                           ) -> PoseEstimate | None:
        """:meth:`find_pose` with the intrinsics test and the map's errors (:meth:`_settled`)
        left to verification (:attr:`PoseEstimate.deferred_settling`): a pose refused for
        its inliers' count, consensus, residuals or spread never pays for the test, whose
        verdict those refusals do not read. ``known``: see :meth:`PoseFinder.find_pose_deferred`
        (the first pool's pose, or the group's before guided matching, is returned as soon
        as ``known`` says it is a solution already verified)."""
        found = self._unsettled_pose(query, candidates, state, known)
        return None if found is None else self._deferred(found, state)

    def _deferred(self, est: PoseEstimate, state: MapState) -> PoseEstimate:
        """``est`` with :meth:`_settled` left in its :attr:`PoseEstimate.deferred_settling`."""
        est.deferred_settling = functools.partial(self._timed_settle, est, state)
        return est

    def _timed_settle(self, est: PoseEstimate, state: MapState) -> None:
        """:meth:`_settled` in place, timed as its own stage: the intrinsics test is a large
        share of a query that otherwise shows in no stage of its timings."""
        start = time.perf_counter()
        self._settled(est, state)
        est.timings["settle"] = est.timings.get("settle", 0.0) + time.perf_counter() - start

    def _settled(self, est: PoseEstimate, state: MapState) -> PoseEstimate:
        """``est`` with the errors it owes to the intrinsics and the map
        (:func:`.map_consistency.settle_pose_errors`; nothing to settle for an estimate
        without inliers)."""
        return settle_pose_errors(est, state, self.conf.kind, self.conf, est.inlier_landmark_ids)

    def _unsettled_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState,
                        known: Callable[[PoseEstimate], bool] | None = None
                        ) -> PoseEstimate | None:
        """:meth:`find_pose` before :meth:`_settled`; with ``known``, the first pose
        ``known`` recognises, as soon as there is one."""
        keyframes = _keyframes_in(candidates, state)
        if not keyframes:
            return None
        timings: dict[str, float] = {}
        feats = self.query_features(query, timings)
        first = self._first_pool(keyframes)
        if len(first) < len(keyframes):
            # A first pose below ``guided_below_inliers`` inliers is set aside for the whole
            # group's: so is one from fewer matches than that, which need not be solved
            # (unless ``known`` may recognise it).
            below = self.conf.guided_below_inliers
            matched = self._match_and_solve(query, feats, first, state, timings,
                                             solve_from=below if known is None else 0)
            seen = _described(matched, first)
            if seen is not None and known is not None and known(seen):
                seen.timings = {**seen.timings, **timings}
                return seen
            if seen is None or (seen.inliers or 0) < below:
                matched = self._match_and_solve(query, feats, keyframes, state, timings)
        else:
            matched = self._match_and_solve(query, feats, keyframes, state, timings)
        q_idx, rows, pool, _ = matched
        est = _described(matched, keyframes)
        if est is None:
            return PoseEstimate(world_from_cam=keyframes[0].world_from_cam.copy(),
                                keyframe_ids=[kf.id for kf in keyframes], num_matches=len(q_idx),
                                inliers=0, timings=timings)
        if (self.conf.guided and (est.inliers or 0) < self.conf.guided_below_inliers
                and (known is None or not known(est))):
            est = self._grow(query, feats, est, keyframes, state, q_idx,
                             pool.landmark_ids[rows])
        est.timings = {**est.timings, **timings}  # every match and solve, guided's own
        return est

    def _match_and_solve(self, query: Frame, feats: Features, keyframes: list[Keyframe],
                         state: MapState, timings: dict[str, float], *, solve_from: int = 0
                         ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], LandmarkPool,
                                    tuple[PoseEstimate, npt.NDArray[np.int64]] | None]:
        """Ratio-test matches to the landmarks of ``keyframes`` and the pose they give
        (:func:`solve_pnp_indexed`, or None); ``timings["match"]`` accumulates. With fewer
        than ``solve_from`` matches no pose is solved (None): its inliers, a subset of the
        matches, could not reach ``solve_from``."""
        start = time.perf_counter()
        prepared = query.cache.get(_pool_key(self.conf.kind, keyframes, state))
        if prepared is not None and prepared.state is not state:
            prepared = None  # gathered in another map state (a frame asked again)
        q_idx, rows, pool = self.match_landmarks(
            feats, keyframes, pool=None if prepared is None else prepared.pool)
        matched = time.perf_counter()
        if len(q_idx) < solve_from:
            timings["match"] = timings.get("match", 0.0) + matched - start
            return q_idx, rows, pool, None
        uncertainty = (pool.uncertainty(state, keyframes, rows) if prepared is None
                       else prepared.uncertainty.take(rows))
        solved = solve_pnp_indexed(feats.keypoints_px[q_idx], pool.points_world[rows],
                                   query.camera, self.conf, uncertainty=uncertainty,
                                   keypoint_scales=self._scales(feats, q_idx))
        timings["match"] = timings.get("match", 0.0) + matched - start
        timings["solve"] = timings.get("solve", 0.0) + time.perf_counter() - matched
        return q_idx, rows, pool, solved

    def _grow(self, query: Frame, feats: Features, est: PoseEstimate, keyframes: list[Keyframe],
              state: MapState, q_idx: npt.NDArray[np.int64],
              landmark_ids: npt.NDArray[np.int64]) -> PoseEstimate:
        """``est`` re-solved on its matches plus those found by projecting the landmarks of
        ``keyframes`` and of the keyframes near ``est`` into the query; ``est`` itself when
        that does not add inliers. The estimate keeps the unguided evidence for the
        false-alarm test."""
        start = time.perf_counter()
        conf = GuidedConf(local_keyframes=self.conf.guided_keyframes)
        ids = [kf.id for kf in keyframes]
        near = state.nearest_keyframes(est.world_from_cam, conf.local_keyframes,
                                       conf.max_view_angle_deg)
        local = keyframes + [state.keyframes[k] for k in near if k not in ids]
        pool = LandmarkPool.gather(local, self.conf.kind)
        radius = conf.window_factor * self.conf.max_reproj_error_px
        g_idx, g_rows = search_by_projection(feats, query.camera, est.world_from_cam,
                                             pool.descriptors, pool.points_world, radius, conf)
        q_all, rows_all = union_matches(g_idx, g_rows, q_idx, pool.rows_of(landmark_ids))
        solved = solve_pnp_indexed(feats.keypoints_px[q_all], pool.points_world[rows_all],
                                   query.camera, self.conf,
                                   uncertainty=pool.uncertainty(state, local, rows_all),
                                   keypoint_scales=self._scales(feats, q_all))
        elapsed = time.perf_counter() - start
        seed = (est.num_matches, int(est.inliers or 0))
        if solved is None or solved[0].inliers is None or solved[0].inliers <= seed[1]:
            est.unguided_evidence = seed
            est.timings["guided"] = elapsed
            return est
        grown, inliers = solved
        # Name the candidates that support the pose (the place finder's answer, as without
        # guided matching); keyframes pulled in around the pose only lent their landmarks.
        supporting = pool.keyframes_of(rows_all[inliers], [kf.id for kf in local])
        grown.keyframe_ids = [k for k in supporting if k in ids] or est.keyframe_ids
        grown.unguided_evidence = seed
        grown.inlier_keypoints = q_all[inliers]
        grown.inlier_landmark_ids = pool.landmark_ids[rows_all[inliers]]
        grown.intrinsics_test = with_unguided_test(grown.intrinsics_test, unguided_positions(
            q_all, rows_all, q_idx, pool.rows_of(landmark_ids)))
        grown.timings = {"solve": est.timings.get("solve", 0.0), "guided": elapsed}
        return grown

    def support(self, query: Frame, world_from_cam: Array, state: MapState) -> Support | None:
        """The query's features of this finder's kind explained by the landmarks of the
        keyframes near ``world_from_cam`` (the local map guided matching projects), in
        windows as guided matching's; None before the features are extracted."""
        feats = query.features.get(self._feature_key)
        if feats is None:
            return None
        conf = GuidedConf(local_keyframes=self.conf.guided_keyframes)
        radius = conf.window_factor * self.conf.max_reproj_error_px
        # The repetition search asks for the first verified pose's support and the
        # uniqueness check asks again (and a later chain step with these features may ask
        # for the same pose): one search per pose, features and map state.
        key = _support_key(self._feature_key, self.conf.kind, radius, conf, world_from_cam)
        cached = query.cache.get(key)
        if (cached is not None and cached.state is state and cached.features is feats
                and cached.camera is query.camera):
            return cached.support
        support = explained_keypoints(feats, query.camera, world_from_cam, state,
                                      self.conf.kind, radius_px=radius, conf=conf)
        query.cache[key] = _CachedSupport(support, feats, state, query.camera)
        return support

    def alternatives(self, query: Frame, estimate: PoseEstimate, state: MapState, *,
                     plausible: Callable[[PoseEstimate], bool] = lambda _: True
                     ) -> list[PoseEstimate]:
        """Poses a repetition of the map offers instead of ``estimate`` (:mod:`.repetition`):
        the pose on the keyframes that what ``estimate`` leaves unexplained points to, and
        those the twins of its landmarks support (landmarks anywhere in the map matched to
        the inliers' query keypoints as closely as Lowe's ratio allows), each grown by guided
        matching over the keyframes its twins came from and those near it; only those
        ``plausible`` as a first pose. Their settling (the intrinsics test) is left to their
        verification (:attr:`PoseEstimate.deferred_settling`)."""
        feats = query.features.get(self._feature_key)
        if feats is None or estimate.inlier_keypoints is None or estimate.inlier_landmark_ids is None:
            return []
        pool, index, ids = self._map_pool(state)
        conf = RepetitionConf(ratio=self.conf.ratio)

        def sigmas_m(rows: npt.NDArray[np.int64]) -> Array:
            return state.landmark_sigmas(pool.landmark_ids[rows], 0.0)

        twins = twin_correspondences(feats, estimate.inlier_keypoints,
                                     estimate.inlier_landmark_ids, pool, index, sigmas_m, conf)
        explained = self.support(query, estimate.world_from_cam, state)
        matched = unexplained_matches(feats, np.zeros(0, np.int64) if explained is None
                                      else explained.keypoints, index, conf)
        grown = self._elsewhere(query, estimate, state, pool.landmark_ids[matched], plausible)
        for alt in alternative_poses(feats, query.camera, twins, pool, self.conf, conf):
            if not plausible(alt):
                continue
            assert alt.inlier_landmark_ids is not None
            alt.keyframe_ids = pool.keyframes_of(pool.rows_of(alt.inlier_landmark_ids), ids)
            # Twins are the few repeated keypoints: the alternative is grown over its own
            # local map, as a first pose with few inliers is (judged on its twin consensus).
            alt = self._grow(query, feats, alt, [state.keyframes[k] for k in alt.keyframe_ids],
                             state, twins[0], pool.landmark_ids[twins[1]])
            grown.append(self._deferred(alt, state))
        return grown

    def _elsewhere(self, query: Frame, estimate: PoseEstimate, state: MapState,
                   landmark_ids: npt.NDArray[np.int64],
                   plausible: Callable[[PoseEstimate], bool]) -> list[PoseEstimate]:
        """The pose found (:meth:`find_pose`) on the keyframes that observe most of
        ``landmark_ids`` (what the keypoints ``estimate`` leaves unexplained match), none of
        ``estimate``'s inlier landmarks and are not in its local map (those see the same
        place), as many as gave it its inliers. Empty when those
        keyframes hold fewer of them than a verified pose needs (a minimal sample and one
        more), or the pose found is not ``plausible``."""
        assert estimate.inlier_landmark_ids is not None
        if len(landmark_ids) == 0:
            return []
        kf_ids, votes = state.landmarks.observing_keyframes(landmark_ids)
        original, _ = state.landmarks.observing_keyframes(estimate.inlier_landmark_ids)
        guided = GuidedConf(local_keyframes=self.conf.guided_keyframes)
        local = state.nearest_keyframes(estimate.world_from_cam, guided.local_keyframes,
                                        guided.max_view_angle_deg)
        away = ~np.isin(kf_ids, original) & ~np.isin(kf_ids, local)
        order = np.argsort(-votes[away], kind="stable")[:max(1, len(estimate.keyframe_ids))]
        if votes[away][order].sum() < estimate.sample_size + 1:
            return []
        far = kf_ids[away][order].tolist()
        found = self._unsettled_pose(query, [PlaceCandidate(int(k), 0.0) for k in far], state)
        # ``plausible`` reads the inliers, the unguided evidence, the inlier threshold, the
        # image size, the sample size and the chance probability, none of which settling
        # (the intrinsics' verdict, the covariances) changes: so the pose is judged before
        # it is settled, and the intrinsics test is left to the verification of a pose
        # that is kept.
        return ([] if found is None or not plausible(found)
                else [self._deferred(found, state)])

    def _map_pool(self, state: MapState) -> tuple[LandmarkPool, RepetitionIndex, list[int]]:
        """The landmarks of every keyframe of ``state`` (:meth:`LandmarkPool.gather`), their
        :class:`RepetitionIndex` and the keyframe ids in pool order: :func:`.map_pool.map_pool`,
        made once per map state (at :meth:`prepare_map`, or by the first query of a later
        one) and shared with the other pose finders of this kind."""
        made = map_pool(state, self.conf.kind, self.conf.repetition_index())
        return made.pool, made.index, made.keyframe_ids

    def _scales(self, feats: Features, q_idx: npt.NDArray[np.int64]) -> Array | None:
        """(M,) localisation scales of query keypoints ``q_idx``: their pyramid levels' with
        ``level_sigmas``, else the reduced image's pixel (``1 / query_scale``) when the
        features come from one, else None (every keypoint to one pixel)."""
        if self.conf.level_sigmas:
            return level_scales(feats.levels[q_idx],
                                feature_lib.level_scale_factor(self.conf.kind))
        if self.conf.query_scale != 1:
            return np.full(len(q_idx), 1.0 / self.conf.query_scale)
        return None

    @property
    def _feature_key(self) -> str:
        """The name the query's features of this finder are cached under on the frame."""
        (key, _), = self.feature_confs().items()
        return key

    def _first_pool(self, keyframes: list[Keyframe]) -> list[Keyframe]:
        """The keyframes whose landmarks are matched first: the best
        ``conf.first_pool_keyframes`` (all of them when None)."""
        first = self.conf.first_pool_keyframes
        return keyframes if first is None else keyframes[:first]

    def prepare_map(self, state: MapState) -> None:
        """Each keyframe's agreement with the map's camera (:mod:`.map_consistency`), which
        the intrinsics test of a query near it reads, and the whole map's landmark pool and
        its index, which the repetition check of every query reads."""
        if self.conf.intrinsics_false_refusal > 0:
            prepare_map(state, self.conf.kind, self.conf)
        self._map_pool(state)

    def query_kinds(self, query: Frame) -> frozenset[str]:
        key = self._feature_key
        return frozenset() if key in query.features else frozenset({key})

    def prepare_query(self, query: Frame) -> dict[str, float]:
        timings: dict[str, float] = {}
        self.query_features(query, timings)
        return timings

    def feature_confs(self) -> dict[str, feature_lib.FeatureConf]:
        conf = feature_lib.FeatureConf(kind=self.conf.kind, max_features=self.conf.max_features,
                                       scale=self.conf.query_scale, grid=self.conf.query_grid)
        return {conf.key: conf}

    def prepare_candidates(self, query: Frame, candidates: list[PlaceCandidate],
                           state: MapState) -> dict[str, float]:
        """The landmark pool :meth:`find_pose` matches first (the best
        ``first_pool_keyframes`` candidates', or the whole group's) and its landmarks' depth
        uncertainty, gathered ahead into ``query.cache``: what the multi relocalizer does on
        its helper thread while this thread extracts the query's features."""
        start = time.perf_counter()
        keyframes = self._first_pool(_keyframes_in(candidates, state))
        if keyframes:
            pool = LandmarkPool.gather(keyframes, self.conf.kind)
            rows = np.arange(len(pool.landmark_ids))
            query.cache[_pool_key(self.conf.kind, keyframes, state)] = _PreparedPool(
                pool, pool.uncertainty(state, keyframes, rows), state)
        return {"pool": time.perf_counter() - start}

    def match_landmarks(self, feats: Features, keyframes: list[Keyframe], *,
                        pool: LandmarkPool | None = None
                        ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], LandmarkPool]:
        """Ratio-test matches of the query ``feats`` to the pooled landmarks of ``keyframes``
        (``pool``: :meth:`LandmarkPool.gather` of them, when already gathered): (M,) query
        indices, (M,) pool rows (one query keypoint per landmark) and the pool."""
        if pool is None:
            pool = LandmarkPool.gather(keyframes, self.conf.kind)
        q_idx, rows, dist = feature_lib.match_ratio(feats.descriptors, pool.descriptors,
                                                    ratio=self.conf.ratio)
        keep = best_per_landmark(pool.landmark_ids[rows], dist, rows, len(pool.landmark_ids))
        return q_idx[keep], rows[keep], pool


def _described(matched: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], LandmarkPool,
                               tuple[PoseEstimate, npt.NDArray[np.int64]] | None],
               keyframes: list[Keyframe]) -> PoseEstimate | None:
    """The pose :meth:`P3PPoseFinder._match_and_solve` gave (None without one), naming its
    inliers' query keypoints, landmarks and the ``keyframes`` that observe them."""
    q_idx, rows, pool, solved = matched
    if solved is None:
        return None
    est, inliers = solved
    est.keyframe_ids = pool.keyframes_of(rows[inliers], [kf.id for kf in keyframes])
    est.inlier_keypoints = q_idx[inliers]
    est.inlier_landmark_ids = pool.landmark_ids[rows[inliers]]
    return est


def _keyframes_in(candidates: list[PlaceCandidate], state: MapState) -> list[Keyframe]:
    """The keyframes of ``candidates`` still in ``state``, in the candidates' order."""
    return [state.keyframes[c.keyframe_id] for c in candidates
            if c.keyframe_id in state.keyframes]


@dataclass(frozen=True)
class _PreparedPool:
    """A pool gathered ahead (:meth:`P3PPoseFinder.prepare_candidates`), the depth
    uncertainty of all its rows and the map state they come from."""

    pool: LandmarkPool
    uncertainty: PointUncertainty
    state: MapState


@dataclass(frozen=True)
class _CachedSupport:
    """A pose's :class:`~.base.Support`, with the features, the map state and the camera
    it was computed with (a hit needs all three to be the same objects)."""

    support: Support
    features: Features
    state: MapState
    camera: Camera


def _support_key(feature_key: str, kind: str, radius_px: float, conf: GuidedConf,
                 world_from_cam: Array) -> str:
    """The ``query.cache`` key of the support of the pose ``world_from_cam`` (its exact
    bytes) for these features and search settings."""
    pose = np.ascontiguousarray(world_from_cam, np.float64).tobytes().hex()
    return f"p3p:support:{feature_key}:{kind}:{radius_px!r}:{conf!r}:{pose}"


def _pool_key(kind: str, keyframes: list[Keyframe], state: MapState) -> str:
    """The ``query.cache`` key of the prepared pool of ``keyframes`` in map ``state``."""
    return f"p3p:pool:{kind}:{state.version}:{','.join(str(kf.id) for kf in keyframes)}"
