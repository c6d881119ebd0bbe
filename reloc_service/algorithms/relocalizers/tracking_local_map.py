"""The local map a tracker matches a query against: the landmarks of the keyframes near the
prior, pooled (:class:`..pose.landmark_pool.LandmarkPool`), and what pooling several
keyframes costs in certainty. A landmark's depth uncertainty is widened by the pose errors
of the keyframes it was triangulated from, and a pose solved on landmarks of several
keyframes is widened to the spread those keyframes' groups show
(:mod:`..pose.cluster_covariance`). The pools of the last few keyframe sets are kept: a
tracked camera sees the same keyframes for many frames, and pooling and weighing their
landmarks costs as much as matching them. A set seen for the first time is put together
from its keyframes' parts (each keyframe's landmark rows, weighed as if it were their
source), kept per keyframe: consecutive priors see nearly the same keyframes in another
order, which is another pool, but the same parts."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.frame import Frame, Keyframe
from ...core.map import MapState
from ...core.numeric import first_occurrences
from ..pose.base import PoseEstimate
from ..pose.cluster_covariance import at_least, cluster_robust_covariance
from ..pose.landmark_keyframe_errors import keyframe_pose_sigmas, widen_for_keyframe_errors
from ..pose.landmark_pool import LandmarkPool, peek_features
from ..pose.point_uncertainty import PointUncertainty
from .multi import STEP_FEATURES

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Local maps (landmark pool and uncertainty of one keyframe set) a tracker keeps: a few
#: cameras tracked at once, each seeing one set for many frames.
LOCAL_MAPS_KEPT = 8
#: Keyframe parts (:class:`KeyframePart`) a tracker keeps: the keyframes of its kept local
#: maps, at the default ``local_keyframes`` (10) each.
KEYFRAME_PARTS_KEPT = 10 * LOCAL_MAPS_KEPT


@dataclass(frozen=True)
class KeyframePart:
    """One keyframe's rows with a landmark (M of them, in its features' order, an id seen
    twice kept twice), as a pool row holds them when this keyframe is their source: landmark
    ids (M,), descriptors (M, D), world points (M, 3), depth sigmas (M,) widened by this
    keyframe's pose error (:func:`landmark_uncertainty`), and the keyframe's centre (3,)."""

    landmark_ids: IntArray
    descriptors: npt.NDArray[Any]
    points_world: Array
    depth_sigmas_m: Array
    centre_world: Array

    @classmethod
    def of(cls, state: MapState, kf_id: int, keyframe: Keyframe, kind: str) -> KeyframePart:
        """The part of keyframe ``kf_id`` (``keyframe``) of ``state`` for ``kind`` landmarks."""
        feats = peek_features(keyframe, kind)
        if feats is None:
            return cls(np.zeros(0, np.int64), np.zeros((0, 0), np.uint8), np.zeros((0, 3)),
                       np.zeros(0), np.asarray(keyframe.position_world, np.float64))
        local = np.flatnonzero(feats.landmark_ids >= 0)
        pool = LandmarkPool(feats.descriptors[local], feats.landmark_ids[local],
                            feats.points_world[local], np.zeros(len(local), np.int64))
        uncertainty = landmark_uncertainty(pool, state, [kf_id], [keyframe])
        return cls(pool.landmark_ids, pool.descriptors, pool.points_world,
                   uncertainty.depth_sigmas_m, np.asarray(keyframe.position_world, np.float64))


def assemble(parts: list[KeyframePart]) -> tuple[LandmarkPool, PointUncertainty]:
    """The pool of the keyframes whose parts are ``parts`` (best first) and its widened depth
    uncertainty: what :meth:`LandmarkPool.gather` and :func:`landmark_uncertainty` give for
    those keyframes, row for row (a landmark's row from the first keyframe that sees it;
    every value a row's own, so taking it from its keyframe's part changes none)."""
    ids = np.concatenate([p.landmark_ids for p in parts])
    first = first_occurrences(ids)
    kf_rows = np.repeat(np.arange(len(parts)), [len(p.landmark_ids) for p in parts])[first]
    # rows ascend by keyframe: each part's picks are one run of ``first``
    offsets = np.cumsum([0] + [len(p.landmark_ids) for p in parts])
    bounds = np.searchsorted(first, offsets)
    picks = [(p, first[lo:hi] - off) for p, lo, hi, off
             in zip(parts, bounds[:-1], bounds[1:], offsets[:-1], strict=True) if hi > lo]
    pool = LandmarkPool(np.concatenate([p.descriptors[i] for p, i in picks]), ids[first],
                        np.concatenate([p.points_world[i] for p, i in picks]),
                        kf_rows.astype(np.int64))
    centres = np.stack([p.centre_world for p in parts])
    return pool, PointUncertainty(np.concatenate([p.depth_sigmas_m[i] for p, i in picks]),
                                  centres[pool.keyframe_rows])


class LocalMaps:
    """The pools of ``kind`` landmarks of the last :data:`LOCAL_MAPS_KEPT` keyframe sets and
    their widened depth uncertainty (:func:`landmark_uncertainty`), and the parts of the last
    :data:`KEYFRAME_PARTS_KEPT` keyframes they were put together from, keyed by map version,
    so an edited map is pooled afresh. Replaced whole, never changed in place: concurrent
    queries read them without a lock (only the engine locks), and a race only pools a set
    or a keyframe once more."""

    def __init__(self) -> None:
        self._kept: dict[tuple[int, tuple[int, ...], str],
                         tuple[LandmarkPool, PointUncertainty]] = {}
        self._parts: dict[tuple[int, int, str], KeyframePart] = {}

    def get(self, state: MapState, near: list[int], keyframes: list[Keyframe], kind: str
            ) -> tuple[LandmarkPool, PointUncertainty]:
        """The pool of ``kind`` landmarks of keyframes ``near`` (``keyframes`` their
        keyframes) in ``state`` and their uncertainty."""
        key = (state.version, tuple(near), kind)
        kept = self._kept.get(key)
        if kept is not None:
            return kept
        parts = self._parts_of(state, near, keyframes, kind)
        if sum(len(p.landmark_ids) for p in parts) == 0:
            pool = LandmarkPool.gather(keyframes, kind)   # the empty pool of its kind
            made = pool, landmark_uncertainty(pool, state, near, keyframes)
        else:
            made = assemble(parts)
        # the last LOCAL_MAPS_KEPT sets made, oldest first
        self._kept = dict([*self._kept.items(), (key, made)][-LOCAL_MAPS_KEPT:])
        return made

    def _parts_of(self, state: MapState, near: list[int], keyframes: list[Keyframe],
                  kind: str) -> list[KeyframePart]:
        """The parts of keyframes ``near``, those not kept made and kept (the last
        :data:`KEYFRAME_PARTS_KEPT` used, oldest first)."""
        kept = self._parts
        keys = [(state.version, k, kind) for k in near]
        parts = [kept.get(key) or KeyframePart.of(state, k, kf, kind)
                 for key, k, kf in zip(keys, near, keyframes, strict=True)]
        used = dict(zip(keys, parts, strict=True))
        self._parts = dict([*((k, v) for k, v in kept.items() if k not in used),
                            *used.items()][-KEYFRAME_PARTS_KEPT:])
        return parts


def landmark_uncertainty(pool: LandmarkPool, state: MapState, keyframe_ids: list[int],
                         keyframes: list[Keyframe]) -> PointUncertainty:
    """The depth uncertainty of every pool landmark, widened by its keyframe's pose error
    (:mod:`..pose.landmark_keyframe_errors`): the landmarks are pooled from several
    keyframes, so a depth that the keypoints alone fix well but a keyframe's pose error
    moves would pull the pooled pose towards that keyframe's error."""
    rows = np.arange(len(pool.landmark_ids))
    rot, pos = keyframe_pose_sigmas(state, keyframe_ids)
    focal = np.array([kf.camera.fx for kf in keyframes], np.float64)
    return widen_for_keyframe_errors(pool.uncertainty(state, keyframes, rows),
                                     pool.points_world, pool.keyframe_rows, rot, pos, focal)


def widen_for_source_keyframes(est: PoseEstimate, inlier_px: Array, inliers_world: Array,
                               query: Frame, source_keyframes: IntArray) -> None:
    """Widen ``est``'s covariance to the spread its inliers' source keyframes show
    (:mod:`..pose.cluster_covariance`): the landmarks are pooled from several keyframes,
    and each group shares its keyframe's pose error, which the model covariance of
    independent residuals does not see."""
    if est.covariance is None:
        return
    robust = cluster_robust_covariance(est.world_from_cam, inlier_px, inliers_world,
                                       query.camera, source_keyframes)
    if robust is not None:
        est.covariance = at_least(est.covariance, robust)


def feature_steps(keyframes: list[Keyframe], kind: str | None, fallback: str | None
                  ) -> list[str]:
    """The query features to track with, in order (names of ``STEP_FEATURES``): ``kind``, or
    ORB where a keyframe of ``keyframes`` has ORB landmarks (the cheap path), else SIFT where
    one has SIFT landmarks; then ``fallback`` where one has its kind of landmarks."""
    first = kind or next((k for k in ("orb", "sift") if has_landmarks(keyframes, k)), None)
    steps = [] if first is None else [first]
    if (fallback is not None and fallback != first
            and has_landmarks(keyframes, STEP_FEATURES[fallback]["kind"])):
        steps.append(fallback)
    return steps


def has_landmarks(keyframes: list[Keyframe], kind: str) -> bool:
    """Whether a keyframe of ``keyframes`` has ``kind`` features with landmarks."""
    for kf in keyframes:
        feats = kf.features.get(kind)
        if feats is not None and bool(np.any(feats.landmark_ids >= 0)):
            return True
    return False
