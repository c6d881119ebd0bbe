"""A keyframe's landmarks as the map knows them without it: each re-triangulated from its
observations in the other keyframes (midpoint, then the reprojection error refined), or, where
a depth map measured it, held at its measured point. What the held-out statistics of
:mod:`.map_consistency` and :mod:`.keyframe_disagreement` test a keyframe against, as a
query's landmarks never saw the query.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core.geometry import invert, transform_points
from ...core.landmark_table import LandmarkColumns
from ...core.map import MapState
from ...core.triangulation import ViewObservations, keypoint_sigmas, refine_points, triangulate_midpoint

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: The most held-out landmarks a keyframe's statistic uses (a query's inliers number a few
#: hundred).
MAX_HELD_OUT = 300


def held_out_candidates(cols: LandmarkColumns, landmark_ids: IntArray
                        ) -> tuple[IntArray, IntArray]:
    """A keyframe's keypoints (indices) whose landmarks (column rows) can be triangulated
    without it, and those rows: two other observations make a held-out point; at most
    :data:`MAX_HELD_OUT` of them, evenly spread over the keyframe's keypoints, make an
    estimate as good as a query's at a fraction of the triangulations."""
    observed = np.flatnonzero(landmark_ids >= 0)
    rows = cols.rows(landmark_ids[observed])
    observed, rows = observed[rows >= 0], rows[rows >= 0]
    enough = np.flatnonzero(np.diff(cols.obs_offsets)[rows] >= 3)
    keep = enough[np.unique(np.linspace(0, len(enough) - 1, min(len(enough), MAX_HELD_OUT))
                            .astype(np.int64))] if len(enough) else enough
    return observed[keep], rows[keep]


#: Reprojection error (pixels) under which an observation is the one a landmark stated exact
#: was lifted from: a point lifted with a depth map reprojects onto its own keypoint to
#: rounding (1e-13 px measured), any other observation by its keypoint noise (0.016 px at the
#: first percentile of two RGB-D maps, a tenth of a pixel and more typically).
SOURCE_REPROJECTION_PX = 1e-6


@dataclass(frozen=True)
class HeldOutViews:
    """What the held-out points of a keyframe's R landmarks are made from
    (:func:`held_out_views`): their observations (of one feature kind) by the other
    keyframes (``others``, one view a keyframe, ``point_index`` into the R) and how many of
    those keyframes see each (``seen``); which are stated exact (``exact``: lifted from a
    depth map, depth sigma 0) and, where any is, their measured points (``measured``,
    (R, 3), read at the exact rows only), their observations by the keyframe itself
    (``own``) and the world centre of each one's anchor keyframe (``anchors``, (R, 3): the
    keyframe of its first observation, from which a snapshot stores its point as a float32
    offset; NaN where that keyframe is not in the map)."""

    others: list[ViewObservations]
    seen: IntArray
    exact: npt.NDArray[np.bool_]
    measured: Array | None = None
    own: list[ViewObservations] = dataclasses.field(default_factory=list)
    anchors: Array | None = None

    def stored_offsets(self) -> npt.NDArray[np.float32]:
        """(E, 3) the measured points of the E exact landmarks as a snapshot stores them by
        default: float32 offsets from their anchor keyframe's centre. A map saved so and
        loaded back gives the very same offsets (its point is that centre plus the offset,
        whose float32 rounding returns the offset), as does one saved with float64 points,
        so the digest of what a statistic read holds across a save: the values a loaded map
        is given are then those computed on the points before their rounding, which moved
        each by at most 1/100 of its uncertainty (the snapshot's bound)."""
        if self.measured is None or self.anchors is None:
            return np.zeros((0, 3), np.float32)
        return (self.measured[self.exact] - self.anchors[self.exact]).astype(np.float32)


def held_out_points(state: MapState, cols: LandmarkColumns, rows: IntArray, kf_id: int,
                    kind: str) -> tuple[Array, npt.NDArray[np.bool_]]:
    """(R, 3) the landmarks of columns ``rows`` as known without keyframe ``kf_id``, and the
    (R,) mask of those known at all (:func:`points_held_out` of :func:`held_out_views`)."""
    return points_held_out(held_out_views(state, cols, rows, kf_id, kind))


def held_out_views(state: MapState, cols: LandmarkColumns, rows: IntArray, kf_id: int,
                   kind: str) -> HeldOutViews:
    """The observations the landmarks of columns ``rows`` are known from without keyframe
    ``kf_id`` (:class:`HeldOutViews`): those of ``kind`` in keyframes of ``state``."""
    kind_index = cols.kinds.index(kind)
    starts, counts = cols.obs_offsets[rows], np.diff(cols.obs_offsets)[rows]
    owner = np.repeat(np.arange(len(rows)), counts)
    run = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
    other_kf, obs_kind, keypoint = cols.obs_keyframe[run], cols.obs_kind[run], cols.obs_keypoint[run]
    of_kind = (obs_kind == kind_index) & np.isin(other_kf, state.keyframe_ids())
    elsewhere = of_kind & (other_kf != kf_id)
    others = _views(state, kind, owner, other_kf, keypoint, elsewhere)
    seen = np.bincount(owner[elsewhere], minlength=len(rows))
    exact = cols.depth_sigmas_m[rows] == 0
    if not exact.any():
        return HeldOutViews(others, seen, exact)
    own = _views(state, kind, owner, other_kf, keypoint, of_kind & (other_kf == kf_id))
    return HeldOutViews(others, seen, exact, cols.points_world[rows], own,
                        _anchor_centres(state, cols.obs_keyframe[starts]))


def _anchor_centres(state: MapState, anchor_ids: IntArray) -> Array:
    """(R, 3) world centres of keyframes ``anchor_ids`` (R,); NaN for an id not in ``state``."""
    centres = np.full((len(anchor_ids), 3), np.nan)
    for i, kf_id in enumerate(anchor_ids.tolist()):
        keyframe = state.keyframes.get(kf_id)
        if keyframe is not None:
            centres[i] = keyframe.world_from_cam[:3, 3]
    return centres


def points_held_out(views: HeldOutViews) -> tuple[Array, npt.NDArray[np.bool_]]:
    """(R, 3) the landmarks ``views`` describes as known without their keyframe, and the
    (R,) mask of those known at all: a landmark lifted from another keyframe's depth map
    (stated exact, depth sigma 0, and reprojecting onto that keyframe's keypoint:
    :func:`_lifted_in`) at its measured point, which the keyframe did not contribute to; one
    lifted from the keyframe's own depth map left out (keypoints seen from nearby cannot
    place it along its ray); any other triangulated from its observations in at least two
    other keyframes (midpoint, then the reprojection error refined)."""
    points = triangulate_midpoint(views.others, len(views.seen))
    held = (views.seen >= 2) & np.isfinite(points).all(axis=1)
    points = refine_points(np.where(held[:, None], points, 1.0), views.others)
    held &= np.isfinite(points).all(axis=1)
    if views.measured is not None:
        measured = views.measured
        elsewhere = _lifted_in(measured, views.exact, views.others)
        here = _lifted_in(measured, views.exact & ~elsewhere, views.own)
        points[elsewhere] = measured[elsewhere]
        held = (held | elsewhere) & ~here
    return points, held


def _views(state: MapState, kind: str, owner: IntArray, keyframe: IntArray, keypoint: IntArray,
           use: npt.NDArray[np.bool_]) -> list[ViewObservations]:
    """The observations ``use`` of points ``owner`` (keypoint ``keypoint`` of ``kind`` in
    keyframe ``keyframe``), one view a keyframe."""
    views = []
    for k in np.unique(keyframe[use]).tolist():
        sel = use & (keyframe == k)
        kf = state.keyframes[k]
        f = kf.features[kind]
        views.append(ViewObservations(kf.camera, invert(kf.world_from_cam), owner[sel],
                                      f.keypoints_px[keypoint[sel]].astype(np.float64),
                                      keypoint_sigmas(f)[keypoint[sel]]))
    return views


def _lifted_in(points_world: Array, exact: npt.NDArray[np.bool_],
               views: list[ViewObservations]) -> npt.NDArray[np.bool_]:
    """(R,) whether each ``exact`` point of (R, 3) ``points_world`` reprojects onto one of its
    observations in ``views`` within :data:`SOURCE_REPROJECTION_PX`: that keyframe's depth
    map measured it."""
    out = np.zeros(len(points_world), bool)
    for v in views:
        sel = exact[v.point_index]
        if not sel.any():
            continue
        owner = v.point_index[sel]
        px = v.camera.project(transform_points(v.cam_from_world, points_world[owner]))
        with np.errstate(invalid="ignore"):
            hit = np.linalg.norm(px - v.pixels_px[sel], axis=1) < SOURCE_REPROJECTION_PX
        out[owner[hit]] = True
    return out
