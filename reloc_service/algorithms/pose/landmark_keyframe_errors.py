"""Landmark depth uncertainty widened by the pose errors of the keyframes it was
triangulated from.

A landmark's stored depth sigma (:func:`~reloc_service.core.triangulation.depth_uncertainty`)
counts only the keypoints' localisation noise ``s`` (the triangulation's
``keypoint_sigma_px``), as if the keyframes' poses were exact. A keyframe whose pose is off by
a rotation ``sigma_r`` (radians) and a position ``sigma_t`` (metres) moves every ray it casts
by about ``f sigma_r + f sigma_t / z`` pixels at depth ``z`` (``f`` its focal in pixels): to
first order an extra, independent localisation error ``e`` of each observation. The depth
sigma is linear in the observations' noise, so the widened sigma is the stored one times
``sqrt(1 + e^2 / s^2)``. Between keyframes a few centimetres apart, whose rays meet at a few
degrees, a pose error of a few tenths of a degree moves a landmark's depth by tens of percent:
seen from a query 30 cm aside, such landmarks pull a pose pooled from several keyframes off
by centimetres unless they are weighted by that uncertainty.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.map import MapState
from ...core.triangulation import TriangulationConf
from .point_uncertainty import PointUncertainty

Array = npt.NDArray[np.float64]


def keyframe_pose_sigmas(state: MapState, keyframe_ids: list[int]) -> tuple[Array, Array]:
    """(K,) rotation sigma (radians) and (K,) position sigma (metres) of each keyframe's pose:
    the largest of the three axes' (the twist's rotation block ``[3:, 3:]`` and translation
    block ``[:3, :3]``); zeros for a keyframe put as exact."""
    covs = state.pose_covariances(keyframe_ids)
    rot = np.sqrt(np.maximum(np.linalg.eigvalsh(covs[:, 3:, 3:])[:, -1], 0.0))
    pos = np.sqrt(np.maximum(np.linalg.eigvalsh(covs[:, :3, :3])[:, -1], 0.0))
    return rot, pos


def widen_for_keyframe_errors(uncertainty: PointUncertainty, points_world: Array,
                              source_rows: npt.NDArray[np.int64], rot_sigma_rad: Array,
                              pos_sigma_m: Array, focal_px: Array, *,
                              keypoint_sigma_px: float = TriangulationConf.keypoint_sigma_px
                              ) -> PointUncertainty:
    """``uncertainty`` of (N, 3) ``points_world`` with each depth sigma widened by the pose
    error of its source keyframe (``source_rows`` (N,) into the (K,) ``rot_sigma_rad``,
    ``pos_sigma_m``, ``focal_px``), as the module describes. Unchanged where every
    keyframe is exact."""
    if not (np.any(rot_sigma_rad > 0) or np.any(pos_sigma_m > 0)):
        return uncertainty
    depth = np.linalg.norm(points_world - uncertainty.ray_origins_world, axis=1)
    rot, pos, f = rot_sigma_rad[source_rows], pos_sigma_m[source_rows], focal_px[source_rows]
    with np.errstate(divide="ignore", invalid="ignore"):
        extra_px2 = f**2 * (rot**2 + np.where(depth > 0, (pos / depth) ** 2, 0.0))
    factor = np.sqrt(1.0 + extra_px2 / keypoint_sigma_px**2)
    return PointUncertainty(uncertainty.depth_sigmas_m * factor, uncertainty.ray_origins_world)
