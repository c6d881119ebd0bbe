"""Where the map repeats around a pose: a periodic wall, a row of identical windows or a second
copy of a picture anywhere gives the landmarks of a pose hypothesis twins, other landmarks of the
map whose descriptors the same query keypoints match about as well. The poses those
twins support are the hypotheses a repetition offers instead; the caller compares them with
the original by what each explains of the whole image (:mod:`.support`).

A twin of inlier ``(keypoint q, landmark L)`` is a landmark ``L'`` of the map, not within
three depth sigmas of ``L``, whose descriptor is as close to ``q``'s as Lowe's ratio test
allows: ``d(q, L') < d(q, L) / ratio``. Had ``L'`` been in the pool the pose was solved from,
the match to ``L`` would have failed the ratio test: the pose rests on a choice the map
does not make.

A copy elsewhere also shows in what the pose leaves unexplained: the query keypoints it does
not explain, matched against the whole map, point at the keyframes of the place the query
was really taken (:func:`unexplained_matches`).

"Nearest" over the whole map is searched in a :class:`~.repetition_index.RepetitionIndex` of
the pool: exact up to its ``exact_rows`` rows, above that the nearest two among the rows
filed near the query descriptor (a twin, as close to the query as its own landmark within
the ratio, lies near it), so a query's cost does not grow with the map.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core import features as feature_lib
from ...core.cameras import Camera
from ...core.frame import Features
from .base import PoseEstimate
from .landmark_pool import LandmarkPool
from .pnp import solve_pnp_indexed
from .pnp_conf import PnPConf
from .repetition_index import RepetitionIndex

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RepetitionConf:
    """How twins are looked for."""

    #: Lowe's ratio of the matcher: a landmark within ``d / ratio`` of a keypoint whose match
    #: is at distance ``d`` would have made that match ambiguous.
    ratio: float = 0.8
    #: Alternative poses solved in turn, each from the twins the previous ones left.
    max_alternatives: int = 2
    #: Inliers whose twins are looked for, evenly chosen among all (a fixed cost: a
    #: repetition gives twins to most inliers on it, so a sample shows it).
    max_inliers: int = 100
    #: Query keypoints a pose leaves unexplained that are matched against the whole map,
    #: evenly chosen among all (a fixed cost; see :func:`unexplained_matches`).
    max_unexplained: int = 200


def twin_correspondences(features: Features, inlier_keypoints: IntArray,
                         inlier_landmark_ids: IntArray, pool: LandmarkPool,
                         index: RepetitionIndex, sigmas_m: Callable[[IntArray], Array],
                         conf: RepetitionConf) -> tuple[IntArray, IntArray]:
    """(T,) query keypoint indices and (T,) ``pool`` rows of the twins of the inliers
    (``inlier_keypoints`` matched to ``inlier_landmark_ids``): for each, the nearest
    descriptor ``index`` (over ``pool``) finds to its keypoint's other than its own landmark,
    when close enough (at most ``conf.max_inliers`` inliers, evenly chosen). ``sigmas_m``:
    the depth sigmas (R,) of pool rows (R,)."""
    empty = np.zeros(0, np.int64)
    own = pool.rows_of(inlier_landmark_ids)
    keep = own >= 0
    if not np.any(keep) or len(pool.landmark_ids) < 2:
        return empty, empty
    q, own = inlier_keypoints[keep], own[keep]
    if len(q) > conf.max_inliers:
        pick = np.unique(np.linspace(0, len(q) - 1, conf.max_inliers).astype(np.int64))
        q, own = q[pick], own[pick]
    desc = features.descriptors[q]
    dist, nearest = index.nearest_two(desc)
    bound = feature_lib.descriptor_distance(desc, pool.descriptors[own]) / conf.ratio
    # The nearest row that is not the inlier's own landmark: a twin if close enough (-1:
    # none found, at distance inf).
    slot = (nearest[:, 0] == own).astype(np.int64)
    twin = nearest[np.arange(len(q)), slot]
    close = (dist[np.arange(len(q)), slot] < bound) & (twin >= 0)
    q, own, twin = q[close], own[close], twin[close]
    gap = np.linalg.norm(pool.points_world[twin] - pool.points_world[own], axis=1)
    apart = gap > 3.0 * (sigmas_m(twin) + sigmas_m(own))
    return q[apart].astype(np.int64), twin[apart].astype(np.int64)


def unexplained_matches(features: Features, explained: IntArray, index: RepetitionIndex,
                        conf: RepetitionConf) -> IntArray:
    """(M,) pool rows (``index``'s) that the query keypoints a pose does not explain (all
    but ``explained``) match under Lowe's ratio test (at most ``conf.max_unexplained`` of
    them, evenly chosen). Where a repeated picture explains the pose, the rest of the image
    (the wall around it, the furniture) is the original place's and matches its landmarks;
    under the right pose what is left is texture without landmarks, whose matches are
    scattered."""
    left = np.setdiff1d(np.arange(len(features)), explained)
    if len(left) > conf.max_unexplained:
        left = left[np.unique(np.linspace(0, len(left) - 1, conf.max_unexplained)
                              .astype(np.int64))]
    if len(left) == 0 or len(index.descriptors) < 2:
        return np.zeros(0, np.int64)
    dist, rows = index.nearest_two(features.descriptors[left])
    keep = (dist[:, 0] < conf.ratio * dist[:, 1]) & (rows[:, 0] >= 0)
    return rows[keep, 0].astype(np.int64)


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
