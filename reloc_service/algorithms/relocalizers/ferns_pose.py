"""The ferns relocalizer's pose from classified keypoints: P3P LO-RANSAC on every keypoint's
candidate landmarks (:mod:`..pose.pnp`), with the match counts and the false-alarm chance
counted per query keypoint rather than per correspondence (a keypoint proposes its ``top_k``
classes and RANSAC may use any one of them), the keyframes seeing the inliers, and the map's
dispersion settled as for the P3P pose finder."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.frame import Frame
from ...core.map import MapState
from ..pose.base import PoseEstimate
from ..pose.map_consistency import settle_pose_errors
from ..pose.pnp import solve_pnp_indexed
from ..pose.pnp_conf import PnPConf
from .base import note_map_calibration

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def classified_pose(query: Frame, px: Array, kp: IntArray, lm: IntArray, points: Array,
                    state: MapState, pnp_conf: PnPConf, kind: str
                    ) -> tuple[PoseEstimate, IntArray] | None:
    """P3P LO-RANSAC on the correspondences (query keypoint ``kp`` at ``px[kp]``, landmark
    ``lm`` at ``points``) and the inlier correspondences' indices; counts are per query
    keypoint (a keypoint with two candidate landmarks is one match), keyframes are those
    seeing the inliers; None without a consensus."""
    solved = solve_pnp_indexed(px[kp], points, query.camera, pnp_conf)
    if solved is None:
        return None
    est, inliers = solved
    est.num_matches = len(np.unique(kp))
    est.inliers = len(np.unique(kp[inliers]))
    est.chance_probability = per_keypoint_chance(est.chance_probability, len(kp),
                                                 est.num_matches)
    est.keyframe_ids = keyframes_seeing(state, lm[inliers])
    note_map_calibration(est, query.camera, state)
    return settle_pose_errors(est, state, kind, pnp_conf, lm[inliers]), inliers


def per_keypoint_chance(p: float | None, correspondences: int, keypoints: int
                        ) -> float | None:
    """Chance that a query keypoint agrees with a wrong pose when it proposes
    ``correspondences / keypoints`` landmarks on average (its ``top_k`` classes) and RANSAC
    may use any of them: ``1 - (1 - p)^c`` for a single correspondence's chance ``p``. The
    false-alarm test counts keypoints, so it must use this, not ``p``."""
    if p is None or keypoints == 0:
        return p
    return float(1.0 - (1.0 - p) ** (correspondences / keypoints))


def keyframes_seeing(state: MapState, landmark_ids: IntArray) -> list[int]:
    """Keyframes observing the most of ``landmark_ids``, most first (ties: lower id)."""
    kf_ids, votes = state.landmarks.observing_keyframes(landmark_ids)
    return kf_ids[np.lexsort((kf_ids, -votes))].tolist()
