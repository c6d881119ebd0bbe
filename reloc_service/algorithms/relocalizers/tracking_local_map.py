"""The local map a tracker matches a query against: the landmarks of the keyframes near the
prior, pooled (:class:`..pose.landmark_pool.LandmarkPool`), and what pooling several
keyframes costs in certainty. A landmark's depth uncertainty is widened by the pose errors
of the keyframes it was triangulated from, and a pose solved on landmarks of several
keyframes is widened to the spread those keyframes' groups show
(:mod:`..pose.cluster_covariance`). The pools of the last few keyframe sets are kept: a
tracked camera sees the same keyframes for many frames, and pooling and weighing their
landmarks costs as much as matching them."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.frame import Frame, Keyframe
from ...core.map import MapState
from ..pose.base import PoseEstimate
from ..pose.cluster_covariance import at_least, cluster_robust_covariance
from ..pose.landmark_keyframe_errors import keyframe_pose_sigmas, widen_for_keyframe_errors
from ..pose.landmark_pool import LandmarkPool
from ..pose.point_uncertainty import PointUncertainty
from .multi import STEP_FEATURES

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Local maps (landmark pool and uncertainty of one keyframe set) a tracker keeps: a few
#: cameras tracked at once, each seeing one set for many frames.
LOCAL_MAPS_KEPT = 8


class LocalMaps:
    """The pools of ``kind`` landmarks of the last :data:`LOCAL_MAPS_KEPT` keyframe sets and
    their widened depth uncertainty (:func:`landmark_uncertainty`), keyed by map version, so
    an edited map is pooled afresh. Replaced whole, never changed in place: concurrent
    queries read it without a lock (only the engine locks), and a race only pools a set once
    more."""

    def __init__(self) -> None:
        self._kept: dict[tuple[int, tuple[int, ...], str],
                         tuple[LandmarkPool, PointUncertainty]] = {}

    def get(self, state: MapState, near: list[int], keyframes: list[Keyframe], kind: str
            ) -> tuple[LandmarkPool, PointUncertainty]:
        """The pool of ``kind`` landmarks of keyframes ``near`` (``keyframes`` their
        keyframes) in ``state`` and their uncertainty."""
        key = (state.version, tuple(near), kind)
        kept = self._kept.get(key)
        if kept is not None:
            return kept
        pool = LandmarkPool.gather(keyframes, kind)
        made = pool, landmark_uncertainty(pool, state, near, keyframes)
        # the last LOCAL_MAPS_KEPT sets made, oldest first
        self._kept = dict([*self._kept.items(), (key, made)][-LOCAL_MAPS_KEPT:])
        return made


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
