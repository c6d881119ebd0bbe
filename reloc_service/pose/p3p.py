"""P3P pose finder (thesis 3.1.3, improved): query features matched to the landmarks of the
top candidate keyframes, then the pose by :mod:`.pnp` (P3P in LO-RANSAC, refined through the
real camera model, with the reprojection RMS and a 6x6 covariance as evidence for
verification)."""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from .. import features as feature_lib
from ..errors import ConfigError
from ..frame import Features, Frame, Keyframe
from ..map import MapState
from ..place.base import PlaceCandidate
from .base import PoseEstimate, PoseFinder, register
from .guided import GuidedConf, search_by_projection
from .kernels import compiled
from .pnp import PnPConf, PointUncertainty, level_scales, solve_pnp_indexed

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

        def __post_init__(self) -> None:
            super().__post_init__()
            feature_lib.FeatureConf(kind=self.kind, max_features=self.max_features)
            if not 0 < self.ratio <= 1:
                raise ConfigError(f"p3p: ratio must be in (0, 1], got {self.ratio}")
            if self.first_pool_keyframes is not None and self.first_pool_keyframes < 1:
                raise ConfigError(f"p3p: first_pool_keyframes must be >= 1 or None, got "
                                  f"{self.first_pool_keyframes}")

    def __init__(self, conf: P3PPoseFinder.Conf) -> None:
        super().__init__(conf)
        self.required_features = frozenset({conf.kind})

    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        """Pose from the landmarks of all ``candidates`` still in ``state``; None if none is.

        When too few matches survive for a pose, the estimate is the best keyframe's pose with
        zero inliers, so the verification refuses it with the counts as the reason."""
        keyframes = _keyframes_in(candidates, state)
        if not keyframes:
            return None
        timings: dict[str, float] = {}
        feats = self.query_features(query, timings)
        first = self._first_pool(keyframes)
        if len(first) < len(keyframes):
            matched = self._match_and_solve(query, feats, first, state, timings)
            solved = matched[3]
            if solved is None or (solved[0].inliers or 0) < self.conf.guided_below_inliers:
                matched = self._match_and_solve(query, feats, keyframes, state, timings)
        else:
            matched = self._match_and_solve(query, feats, keyframes, state, timings)
        q_idx, rows, pool, solved = matched
        if solved is None:
            return PoseEstimate(world_from_cam=keyframes[0].world_from_cam.copy(),
                                keyframe_ids=[kf.id for kf in keyframes], num_matches=len(q_idx),
                                inliers=0, timings=timings)
        est, inliers = solved
        est.keyframe_ids = pool.keyframes_of(rows[inliers], [kf.id for kf in keyframes])
        if self.conf.guided and (est.inliers or 0) < self.conf.guided_below_inliers:
            est = self._grow(query, feats, est, keyframes, state, q_idx,
                             pool.landmark_ids[rows])
        est.timings = {**est.timings, **timings}  # every match and solve, guided's own
        return est

    def _match_and_solve(self, query: Frame, feats: Features, keyframes: list[Keyframe],
                         state: MapState, timings: dict[str, float]
                         ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], LandmarkPool,
                                    tuple[PoseEstimate, npt.NDArray[np.int64]] | None]:
        """Ratio-test matches to the landmarks of ``keyframes`` and the pose they give
        (:func:`solve_pnp_indexed`, or None); ``timings["match"]`` accumulates."""
        start = time.perf_counter()
        prepared = query.cache.get(_pool_key(self.conf.kind, keyframes, state))
        if prepared is not None and prepared.state is not state:
            prepared = None  # gathered in another map state (a frame asked again)
        q_idx, rows, pool = self.match_landmarks(
            feats, keyframes, pool=None if prepared is None else prepared.pool)
        matched = time.perf_counter()
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
        q_all, rows_all = _union(g_idx, g_rows, q_idx, pool.rows_of(landmark_ids))
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
        grown.timings = {"solve": est.timings.get("solve", 0.0), "guided": elapsed}
        return grown

    def _scales(self, feats: Features, q_idx: npt.NDArray[np.int64]) -> Array | None:
        """(M,) pyramid-level scales of query keypoints ``q_idx`` with ``level_sigmas``."""
        if not self.conf.level_sigmas:
            return None
        return level_scales(feats.levels[q_idx], feature_lib.level_scale_factor(self.conf.kind))

    def _first_pool(self, keyframes: list[Keyframe]) -> list[Keyframe]:
        """The keyframes whose landmarks are matched first: the best
        ``conf.first_pool_keyframes`` (all of them when None)."""
        first = self.conf.first_pool_keyframes
        return keyframes if first is None else keyframes[:first]

    def query_kinds(self, query: Frame) -> frozenset[str]:
        return frozenset() if self.conf.kind in query.features else self.required_features

    def prepare_query(self, query: Frame) -> dict[str, float]:
        timings: dict[str, float] = {}
        self.query_features(query, timings)
        return timings

    def feature_confs(self) -> dict[str, feature_lib.FeatureConf]:
        return {self.conf.kind: feature_lib.FeatureConf(kind=self.conf.kind,
                                                        max_features=self.conf.max_features)}

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
        keep = _best_per_landmark(pool.landmark_ids[rows], dist, rows, len(pool.landmark_ids))
        return q_idx[keep], rows[keep], pool


@dataclass(frozen=True)
class LandmarkPool:
    """The landmarks seen by some keyframes, one row per landmark (L rows): the descriptor of
    its observation in the best-ranked keyframe, its id, world point and that keyframe."""

    descriptors: npt.NDArray[Any]
    landmark_ids: npt.NDArray[np.int64]
    points_world: Array
    keyframe_rows: npt.NDArray[np.int64]

    @classmethod
    def gather(cls, keyframes: list[Keyframe], kind: str) -> LandmarkPool:
        """Pool ``kind`` landmarks of ``keyframes`` (best first). A landmark seen by several
        keyframes keeps one row: duplicates would fail Lowe's ratio test against themselves."""
        feats = [kf.features.get(kind) for kf in keyframes]
        if len(feats) == 1 and feats[0] is not None and len(feats[0]):
            f = feats[0]
            idx = _landmark_rows(f)
            return cls(f.descriptors[idx], f.landmark_ids[idx], f.points_world[idx],
                       np.zeros(len(idx), np.int64))
        local = [np.zeros(0, np.int64) if f is None else np.flatnonzero(f.landmark_ids >= 0)
                 for f in feats]
        if not sum(len(i) for i in local):
            width = 128 if kind == "sift" else 32     # both kinds are uint8 descriptors
            return cls(np.zeros((0, width), np.uint8), np.zeros(0, np.int64), np.zeros((0, 3)),
                       np.zeros(0, np.int64))
        ids = np.concatenate([f.landmark_ids[i] for f, i in zip(feats, local, strict=True)
                              if f is not None])
        kf_rows = np.repeat(np.arange(len(feats)), [len(i) for i in local])
        # The first occurrence is in the best-ranked keyframe; sorted, rows stay grouped by
        # keyframe, so only the kept descriptors are copied (not every observation's).
        first = np.sort(np.unique(ids, return_index=True)[1])
        rows, idx = kf_rows[first], np.concatenate(local)[first]
        picks = [(feats[r], idx[rows == r]) for r in np.unique(rows)]
        return cls(np.concatenate([f.descriptors[i] for f, i in picks if f is not None]),
                   ids[first], np.concatenate([f.points_world[i] for f, i in picks
                                               if f is not None]), rows)

    def uncertainty(self, state: MapState, keyframes: list[Keyframe],
                    rows: npt.NDArray[np.int64]) -> PointUncertainty:
        """The depth uncertainty of the landmarks of pool ``rows`` (``keyframes`` as given to
        :meth:`gather`), along the rays from the keyframe each row came from."""
        sigmas = state.landmark_sigmas(self.landmark_ids[rows], 0.0)
        centres = np.array([kf.position_world for kf in keyframes]).reshape(-1, 3)
        return PointUncertainty(sigmas, centres[self.keyframe_rows[rows]])

    def rows_of(self, landmark_ids: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        """(M,) pool row of each landmark id; -1 where the pool does not hold it."""
        if len(self.landmark_ids) == 0:
            return np.full(len(landmark_ids), -1, np.int64)
        order = np.argsort(self.landmark_ids, kind="stable")
        pos = np.clip(np.searchsorted(self.landmark_ids[order], landmark_ids), 0, len(order) - 1)
        return np.where(self.landmark_ids[order][pos] == landmark_ids, order[pos], -1
                        ).astype(np.int64)

    def keyframes_of(self, rows: npt.NDArray[np.int64], keyframe_ids: list[int]) -> list[int]:
        """Ids of the keyframes whose landmarks (pool ``rows``) gave inliers, most first."""
        counts = np.bincount(self.keyframe_rows[rows], minlength=len(keyframe_ids))
        order = np.argsort(-counts, kind="stable")
        return [keyframe_ids[i] for i in order if counts[i] > 0]


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


def _pool_key(kind: str, keyframes: list[Keyframe], state: MapState) -> str:
    """The ``query.cache`` key of the prepared pool of ``keyframes`` in map ``state``."""
    return f"p3p:pool:{kind}:{state.version}:{','.join(str(kf.id) for kf in keyframes)}"


#: Per keyframe features: the rows :meth:`LandmarkPool.gather` keeps of it alone (a few
#: kB each, weakly held: gone with the features). Features are never changed in place
#: (:meth:`Features.with_landmarks` copies), so the rows stay right while they live.
_LANDMARK_ROWS: weakref.WeakKeyDictionary[Features, npt.NDArray[np.int64]] = (
    weakref.WeakKeyDictionary())


def _landmark_rows(features: Features) -> npt.NDArray[np.int64]:
    """Rows of ``features`` with a landmark, the first row of each landmark id (ascending):
    the rows a pool of this keyframe alone holds. Computed once per features object (the
    fast path pools the best keyframe alone for every query)."""
    rows = _LANDMARK_ROWS.get(features)
    if rows is None:
        local = np.flatnonzero(features.landmark_ids >= 0)
        rows = local[np.sort(np.unique(features.landmark_ids[local], return_index=True)[1])]
        rows.flags.writeable = False
        _LANDMARK_ROWS[features] = rows
    return rows


def _union(first_q: npt.NDArray[np.int64], first_rows: npt.NDArray[np.int64],
           second_q: npt.NDArray[np.int64], second_rows: npt.NDArray[np.int64]
           ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Correspondences (query index, pool row) of both lists, the first list winning where a
    query keypoint or a pool row appears in both; rows of -1 are dropped."""
    q = np.concatenate([first_q, second_q])
    rows = np.concatenate([first_rows, second_rows])
    valid = np.flatnonzero(rows >= 0)
    keep = np.sort(valid[np.unique(q[valid], return_index=True)[1]])
    keep = np.sort(keep[np.unique(rows[keep], return_index=True)[1]])
    return q[keep], rows[keep]


def _best_per_landmark(landmark_ids: npt.NDArray[np.int64], dist: npt.NDArray[np.float32],
                       rows: npt.NDArray[np.int64] | None = None, pool_size: int = 0
                       ) -> npt.NDArray[np.int64]:
    """Indices of the matches to keep: for each landmark, the query keypoint nearest to it
    (the first of equally near ones). With the matches' pool ``rows`` (one row per landmark,
    ``pool_size`` rows), one compiled pass where numba is installed (:mod:`.kernels`)."""
    kernels = compiled()
    if kernels is not None and rows is not None:
        keep = np.empty(len(rows), np.int64)
        count = kernels.best_per_row(np.ascontiguousarray(rows, np.int64),
                                     np.ascontiguousarray(dist, np.float32),
                                     np.full(pool_size, -1, np.int64), keep)
        return keep[:count]
    order = np.lexsort((dist, landmark_ids))
    _, first = np.unique(landmark_ids[order], return_index=True)
    return np.sort(order[first])
