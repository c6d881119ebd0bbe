"""The keyframes' pose uncertainty carried into a relocalized pose.

A keyframe put with a pose that is off by ``exp(eps)`` (right perturbation of
``world_from_kf``) places every landmark it fixes off by the same rigid motion of the world,
``world_from_kf @ exp(eps) @ kf_from_world = exp(Ad(world_from_kf) eps)``; a query pose solved
on those landmarks moves with them, ``exp(Ad(world_from_kf) eps) @ world_from_cam =
world_from_cam @ exp(Ad(cam_from_kf) eps)``. Keyframe k's covariance ``S_k`` thus reaches the
query as ``A_k S_k A_k^T`` with ``A_k = Ad(cam_from_kf)`` (:func:`~reloc_service.core.geometry.se3_adjoint`):
its translation part grows with the lever arm from the keyframe to the query, by the
keyframe's rotation uncertainty.

Several keyframes fix the landmarks of one pose: each landmark is placed by the keyframes
that observe it (triangulated from their rays, or lifted from one's depth and confirmed by
the others), so keyframe k's share ``w_k`` is the part of the inliers' observations it holds,
and the pose moves by about ``sum_k w_k A_k eps_k``. The keyframes of one neighbourhood come
from one stretch of the trajectory and share most of their error (a visual-inertial
odometry's drift, a ground-truth system's calibration), so the errors are taken as fully
correlated: the covariance is the share-weighted mean ``sum_k w_k A_k S_k A_k^T``, exact to
first order for one keyframe and for keyframes that share one error. Were they independent
instead, rotations would partly cancel (down to ``sum_k w_k^2 A_k S_k A_k^T``) while the
position, which landmark sets moving differently also shift, cancels less: the Monte-Carlo
tests (tests/test_map_uncertainty.py) measure such spreads between half and 1.3 times the
stated sigmas.

This part of a pose's uncertainty is independent of the query's keypoint noise and of the
landmarks' depth noise (:mod:`.pnp`), so the answer's covariance is their sum
(:attr:`.base.PoseEstimate.map_covariance`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.geometry import invert, se3_adjoints
from ...core.map import MapState

Array = npt.NDArray[np.float64]


def keyframe_shares(state: MapState, landmark_ids: npt.ArrayLike
                    ) -> tuple[npt.NDArray[np.int64], Array]:
    """(K,) keyframe ids and (K,) shares (summing to one) of the observations of the
    landmarks ``landmark_ids`` each keyframe of ``state`` holds; empty arrays when none of
    them is a landmark of ``state``."""
    ids = np.asarray(landmark_ids, np.int64).ravel()
    if len(ids) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    kf_ids, votes = state.landmarks.observing_keyframes(ids)
    present = np.array([k in state.keyframes for k in kf_ids.tolist()], bool)
    kf_ids, votes = kf_ids[present], votes[present].astype(np.float64)
    total = votes.sum()
    if total <= 0:
        return np.zeros(0, np.int64), np.zeros(0)
    return kf_ids, votes / total


def transported_covariance(world_from_cam: Array, world_from_kfs: Array, covariances: Array,
                           shares: Array) -> Array:
    """(6, 6) covariance of ``world_from_cam`` (twist (rho, omega), right perturbation) from
    the (K, 6, 6) covariances of keyframe poses ``world_from_kfs`` (K, 4, 4), each moved to
    the query by the adjoint of ``cam_from_kf`` and weighed by its share (K,) (see the
    module docstring for why a weighted mean)."""
    cam_from_world = invert(world_from_cam)
    adjoints = se3_adjoints(cam_from_world[None] @ np.asarray(world_from_kfs, np.float64))
    moved = adjoints @ np.asarray(covariances, np.float64) @ adjoints.transpose(0, 2, 1)
    out = np.einsum("k,kij->ij", np.asarray(shares, np.float64), moved)
    return np.asarray(0.5 * (out + out.T), np.float64)


def map_covariance(world_from_cam: Array, state: MapState, landmark_ids: npt.ArrayLike
                   ) -> Array | None:
    """(6, 6) covariance that the poses of the keyframes observing the landmarks
    ``landmark_ids`` (a pose's inliers) give ``world_from_cam``; None when none of them is a
    landmark of ``state``. Keyframes without a covariance of their own take the map's
    default (:meth:`~reloc_service.core.map.MapState.pose_covariances`)."""
    kf_ids, shares = keyframe_shares(state, landmark_ids)
    if len(kf_ids) == 0:
        return None
    poses = np.stack([state.keyframes[k].world_from_cam for k in kf_ids.tolist()])
    return transported_covariance(world_from_cam, poses, state.pose_covariances(kf_ids.tolist()),
                                  shares)


def keyframes_covariance(world_from_cam: Array, state: MapState, keyframe_ids: list[int],
                         weights: npt.ArrayLike) -> Array | None:
    """(6, 6) covariance that the poses of ``keyframe_ids`` give ``world_from_cam`` when the
    pose rests on them directly (solved against their rays, as the five-point finder does),
    each by its share of ``weights`` (K,) (e.g. inliers per keyframe); None when no keyframe
    with a positive weight is in ``state``."""
    w = np.asarray(weights, np.float64)
    keep = [i for i, k in enumerate(keyframe_ids) if k in state.keyframes and w[i] > 0]
    if not keep:
        return None
    ids = [keyframe_ids[i] for i in keep]
    poses = np.stack([state.keyframes[k].world_from_cam for k in ids])
    return transported_covariance(world_from_cam, poses, state.pose_covariances(ids),
                                  w[keep] / w[keep].sum())
