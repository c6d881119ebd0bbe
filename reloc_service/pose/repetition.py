"""Where the map repeats around a pose: a periodic wall, a row of identical windows or a second
copy of a picture nearby gives the landmarks of a pose hypothesis twins, other landmarks of the
local map whose descriptors the same query keypoints match about as well. The poses those
twins support are the hypotheses a repetition offers instead; the caller compares them with
the original by what each explains of the whole image (:mod:`.support`).

A twin of inlier ``(keypoint q, landmark L)`` is a landmark ``L'`` of the local map, not within
three depth sigmas of ``L``, whose descriptor is as close to ``q``'s as Lowe's ratio test
allows: ``d(q, L') < d(q, L) / ratio``. Had ``L'`` been in the pool the pose was solved from,
the match to ``L`` would have failed the ratio test: the pose rests on a choice the local map
does not make.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..cameras import Camera
from ..frame import Features, is_binary_descriptor
from .base import PoseEstimate
from .landmark_pool import LandmarkPool
from .pnp import PnPConf, solve_pnp_indexed

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RepetitionConf:
    """How twins are looked for."""

    #: Lowe's ratio of the matcher: a landmark within ``d / ratio`` of a keypoint whose match
    #: is at distance ``d`` would have made that match ambiguous.
    ratio: float = 0.8
    #: Twins kept per inlier (nearest first): a periodic texture offers one per period.
    per_inlier: int = 3
    #: Alternative poses solved in turn, each from the twins the previous ones left.
    max_alternatives: int = 2


def twin_correspondences(features: Features, inlier_keypoints: IntArray,
                         inlier_landmark_ids: IntArray, pool: LandmarkPool,
                         pool_sigmas_m: Array, conf: RepetitionConf) -> tuple[IntArray, IntArray]:
    """(T,) query keypoint indices and (T,) ``pool`` rows of the twins of the inliers
    (``inlier_keypoints`` matched to ``inlier_landmark_ids``); ``pool_sigmas_m`` (P,) the
    pool landmarks' depth sigmas."""
    empty = np.zeros(0, np.int64)
    own = pool.rows_of(inlier_landmark_ids)
    keep = own >= 0
    if not np.any(keep) or len(pool.landmark_ids) < 2:
        return empty, empty
    q, own = inlier_keypoints[keep], own[keep]
    found_q, found_rows = [], []
    for start in range(0, len(q), _CHUNK):  # bounded memory: (chunk, P) distances at a time
        chunk = slice(start, start + _CHUNK)
        tq, trows = _twins_of(features.descriptors[q[chunk]], own[chunk], pool, pool_sigmas_m,
                              conf)
        found_q.append(q[chunk][tq])
        found_rows.append(trows)
    return np.concatenate(found_q).astype(np.int64), np.concatenate(found_rows).astype(np.int64)


#: Inliers whose distances to the pool are computed at once.
_CHUNK = 64


def _twins_of(query_desc: npt.NDArray[Any], own: IntArray, pool: LandmarkPool,
              pool_sigmas_m: Array, conf: RepetitionConf) -> tuple[IntArray, IntArray]:
    """(T,) rows of ``query_desc`` and (T,) pool rows of their twins (``own``: the pool row
    each is matched to)."""
    dist = descriptor_distances(query_desc, pool.descriptors)  # (I, P)
    bound = dist[np.arange(len(own)), own] / conf.ratio
    dist[np.arange(len(own)), own] = np.inf
    k = min(conf.per_inlier, dist.shape[1])
    nearest = np.argpartition(dist, k - 1, axis=1)[:, :k]
    close = np.take_along_axis(dist, nearest, axis=1) < bound[:, None]
    gap = np.linalg.norm(pool.points_world[nearest] - pool.points_world[own][:, None, :], axis=2)
    apart = gap > 3.0 * (pool_sigmas_m[nearest] + pool_sigmas_m[own][:, None])
    rows, slots = np.nonzero(close & apart)
    return rows.astype(np.int64), nearest[rows, slots].astype(np.int64)


def alternative_poses(features: Features, camera: Camera, twins: tuple[IntArray, IntArray],
                      pool: LandmarkPool, pnp_conf: PnPConf, conf: RepetitionConf
                      ) -> list[PoseEstimate]:
    """Up to ``conf.max_alternatives`` poses the ``twins`` correspondences support, each solved
    (P3P LO-RANSAC, :func:`solve_pnp_indexed`) from those the previous ones did not use."""
    q, rows = twins
    found: list[PoseEstimate] = []
    while len(found) < conf.max_alternatives and len(q) >= 4:
        solved = solve_pnp_indexed(features.keypoints_px[q], pool.points_world[rows], camera,
                                   pnp_conf)
        if solved is None:
            break
        estimate, inliers = solved
        estimate.inlier_keypoints = q[inliers]
        estimate.inlier_landmark_ids = pool.landmark_ids[rows[inliers]]
        found.append(estimate)
        rest = np.setdiff1d(np.arange(len(q)), inliers)
        q, rows = q[rest], rows[rest]
    return found


def descriptor_distances(a: npt.NDArray[Any], b: npt.NDArray[Any]) -> Array:
    """(A, B) distances between descriptors: Hamming for binary ones (ORB), L2 for others.
    For a few rows ``a`` against a pool: (A, B, words) for ORB, one product for SIFT."""
    if is_binary_descriptor(a):
        wa = np.ascontiguousarray(a).view(np.uint64) if a.shape[1] % 8 == 0 else None
        wb = np.ascontiguousarray(b).view(np.uint64) if b.shape[1] % 8 == 0 else None
        if wa is not None and wb is not None:
            return np.bitwise_count(wa[:, None, :] ^ wb[None, :, :]).sum(
                axis=2, dtype=np.int64).astype(np.float64)
        bits_a, bits_b = np.unpackbits(a, axis=1), np.unpackbits(b, axis=1)
        return (bits_a[:, None, :] != bits_b[None, :, :]).sum(axis=2).astype(np.float64)
    fa, fb = a.astype(np.float32), b.astype(np.float32)
    d2 = (fa * fa).sum(1)[:, None] + (fb * fb).sum(1)[None, :] - 2.0 * fa @ fb.T
    return np.sqrt(np.maximum(d2, 0.0)).astype(np.float64)
