"""A new keyframe's landmarks in the map: its features matched to its neighbours' (mutual ratio
test, checked against the known epipolar geometry), existing tracks extended into it and into
the neighbours, new landmarks triangulated from the tracks (:mod:`.triangulation`) or lifted
from the keyframe's depth map, then refined over all their observations."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from .cameras import Camera
from .features import match_ratio
from .frame import Keyframe, is_binary_descriptor
from .geometry import invert
from .map import KeyframeMap, MapState
from .triangulation import (
    TrackStatus,
    TriangulationConf,
    TriangulationStats,
    ViewObservations,
    epipolar_angles,
    keypoint_sigmas,
    observation_faults,
    refine_points,
    reprojection_errors,
    rotate_points,
    to_camera,
    triangulate_tracks,
)

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


# -- depth ------------------------------------------------------------------------------------

def sample_depth(depth: npt.NDArray[np.floating], pixels_px: Array, *,
                 interpolation: str = "bilinear", max_jump: float = 0.03
                 ) -> tuple[Array, npt.NDArray[np.bool_]]:
    """Z-depth (N,) at pixels (N, 2) of a (H, W) depth map (NaN or <= 0: unknown) and the mask
    of valid values: all four surrounding pixels known and within ``max_jump`` (relative) of
    each other, so no value is interpolated across a depth discontinuity."""
    h, w = depth.shape
    px = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        x0 = np.floor(px[:, 0])
        y0 = np.floor(px[:, 1])
        inside = (x0 >= 0) & (y0 >= 0) & (x0 <= w - 2) & (y0 <= h - 2)
    xi = np.where(inside, x0, 0).astype(np.int64)
    yi = np.where(inside, y0, 0).astype(np.int64)
    quad = np.stack([depth[yi, xi], depth[yi, xi + 1], depth[yi + 1, xi], depth[yi + 1, xi + 1]],
                    axis=1).astype(np.float64)
    known = inside & np.all(np.isfinite(quad) & (quad > 0), axis=1)
    quad = np.where(known[:, None], quad, 1.0)
    smooth = (quad.max(axis=1) - quad.min(axis=1)) <= max_jump * quad.min(axis=1)
    fx = np.where(inside, px[:, 0] - x0, 0.0)
    fy = np.where(inside, px[:, 1] - y0, 0.0)
    if interpolation == "nearest":
        corner = (fy >= 0.5).astype(np.int64) * 2 + (fx >= 0.5).astype(np.int64)
        z = quad[np.arange(len(quad)), corner]
    else:
        weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
        z = np.einsum("ij,ij->i", quad, weights)
    valid = known & smooth
    return np.where(valid, z, np.nan), valid


def lift_pixels(camera: Camera, world_from_cam: Array, pixels_px: Array, z: Array) -> Array:
    """(N, 3) world points at Z-depth ``z`` (N,) behind pixels (N, 2); NaN where the ray does
    not point forward."""
    bearings = camera.unproject(pixels_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        p_cam = bearings / np.where(bearings[:, 2:3] > 1e-9, bearings[:, 2:3], np.nan) * z[:, None]
    return rotate_points(p_cam, world_from_cam[:3, :3]) + world_from_cam[:3, 3]


def landmarks_from_depth(keyframe: Keyframe, kind: str, conf: TriangulationConf | None = None
                         ) -> tuple[IntArray, Array]:
    """Keypoints of ``keyframe.features[kind]`` without a landmark that have a valid depth
    (see :func:`sample_depth`, range ``[min_depth_m, max_depth_m]``): their indices (M,) and
    world points (M, 3). Empty when the keyframe has no depth map."""
    conf = conf or TriangulationConf()
    feats = keyframe.features.get(kind)
    if keyframe.depth is None or feats is None or len(feats) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    free = np.flatnonzero(~feats.has_landmark)
    px = feats.keypoints_px[free]
    z, valid = sample_depth(keyframe.depth, px, interpolation=conf.depth_interpolation,
                            max_jump=conf.max_depth_jump)
    with np.errstate(invalid="ignore"):
        valid &= (z >= conf.min_depth_m) & (z <= conf.max_depth_m)
    points = lift_pixels(keyframe.camera, keyframe.world_from_cam, px[valid], z[valid])
    finite = np.isfinite(points).all(axis=1)
    return free[valid][finite].astype(np.int64), points[finite]


# -- matching two keyframes -------------------------------------------------------------------

def match_keyframes(kf_a: Keyframe, kf_b: Keyframe, kind: str, conf: TriangulationConf
                    ) -> tuple[IntArray, IntArray, int]:
    """One-to-one ratio-test matches (mutual nearest neighbours if ``conf.mutual``) between the
    ``kind`` features of two posed keyframes that lie within ``max_epipolar_px`` (times the
    keypoints' scale) of their epipolar lines: (indices in a (M,), indices in b (M,), number
    of matches before the epipolar check)."""
    fa, fb = kf_a.features.get(kind), kf_b.features.get(kind)
    empty = np.zeros(0, np.int64)
    if fa is None or fb is None or len(fa) == 0 or len(fb) < 2:
        return empty, empty, 0
    ia, ib, dist = match_ratio(fa.descriptors, fb.descriptors, ratio=conf.ratio)
    order = np.lexsort((dist, ib))              # best match per keypoint of b
    first = np.r_[True, ib[order][1:] != ib[order][:-1]] if len(order) else np.zeros(0, bool)
    ia, ib = ia[order[first]], ib[order[first]]
    if conf.mutual and len(ia):
        mutual = _nearest_in(fa.descriptors, fb.descriptors[ib]) == ia
        ia, ib = ia[mutual], ib[mutual]
    b_from_a = invert(kf_b.world_from_cam) @ kf_a.world_from_cam
    angles = epipolar_angles(kf_a.camera.unproject(fa.keypoints_px[ia]),
                             kf_b.camera.unproject(fb.keypoints_px[ib]), b_from_a)
    focal = 0.5 * (np.sqrt(kf_a.camera.fx * kf_a.camera.fy)
                   + np.sqrt(kf_b.camera.fx * kf_b.camera.fy))
    sigma = np.maximum(keypoint_sigmas(fa)[ia], keypoint_sigmas(fb)[ib])
    keep = angles <= conf.max_epipolar_px * sigma / focal
    return ia[keep], ib[keep], len(ia)


def _nearest_in(train: npt.NDArray[Any], query: npt.NDArray[Any]) -> IntArray:
    """(M,) index of the nearest ``train`` descriptor of each ``query`` descriptor (Hamming
    for binary uint8 descriptors, L2 otherwise)."""
    binary = is_binary_descriptor(train)
    dtype = np.uint8 if binary else np.float32       # batchDistance's L2 needs float32
    _, nearest = cv2.batchDistance(np.ascontiguousarray(query, dtype),
                                   np.ascontiguousarray(train, dtype),
                                   cv2.CV_32S if binary else cv2.CV_32F,
                                   normType=cv2.NORM_HAMMING if binary else cv2.NORM_L2, K=1)
    return nearest[:, 0].astype(np.int64)


@dataclass(frozen=True, eq=False)
class _Matches:
    """Matches of the new keyframe's keypoints ``i`` to keypoints ``j`` of keyframe ``other``."""

    other: IntArray
    i: IntArray
    j: IntArray

    def rows_of(self, kf_id: int) -> IntArray:
        return np.flatnonzero(self.other == kf_id)


def _match_neighbours(state: MapState, keyframe: Keyframe, neighbour_ids: Iterable[int],
                      kind: str, conf: TriangulationConf, stats: TriangulationStats) -> _Matches:
    others, ii, jj = [], [], []
    for n in neighbour_ids:
        if n == keyframe.id or n not in state.keyframes:
            continue
        i, j, raw = match_keyframes(keyframe, state.keyframes[n], kind, conf)
        stats.matches += raw
        stats.epipolar_inliers += len(i)
        others.append(np.full(len(i), n, np.int64))
        ii.append(i)
        jj.append(j)
    if not others:
        empty = np.zeros(0, np.int64)
        return _Matches(empty, empty, empty)
    return _Matches(np.concatenate(others), np.concatenate(ii), np.concatenate(jj))


def _landmark_of(state: MapState, matches: _Matches, kind: str) -> IntArray:
    """(M,) landmark id of each matched keypoint of the other keyframe (-1: none)."""
    out = np.full(len(matches.i), -1, np.int64)
    for n in np.unique(matches.other):
        rows = matches.rows_of(int(n))
        out[rows] = state.keyframes[int(n)].features[kind].landmark_ids[matches.j[rows]]
    return out


def _pixel_errors(keyframe: Keyframe, points_world: Array, pixels_px: Array) -> Array:
    """(M,) reprojection errors (px) of world points at pixels of ``keyframe``; inf behind."""
    p_cam = to_camera(invert(keyframe.world_from_cam), points_world)
    err = np.linalg.norm(keyframe.camera.project(p_cam) - pixels_px, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def _first_unique(keys: Sequence[IntArray], order: IntArray) -> IntArray:
    """Rows (in ``order``) kept so that each key array has no repeated value, first wins."""
    rows = order
    for key in keys:
        _, first = np.unique(key[rows], return_index=True)
        rows = rows[np.sort(first)]
    return rows


# -- the keyframe-level steps -----------------------------------------------------------------

def _extend_into_keyframe(kmap: KeyframeMap, kf_id: int, kind: str, matches: _Matches,
                          conf: TriangulationConf) -> IntArray:
    """Attach the new keyframe's free keypoints to the landmarks of their matches that
    reproject within the threshold; returns the landmark ids extended."""
    state = kmap.snapshot()
    kf = state.keyframe(kf_id)
    feats = kf.features[kind]
    lm = _landmark_of(state, matches, kind)
    rows = np.flatnonzero((lm >= 0) & (feats.landmark_ids[matches.i] < 0)
                          & ~np.isin(lm, feats.landmark_ids))
    if len(rows) == 0:
        return np.zeros(0, np.int64)
    err = _pixel_errors(kf, state.landmark_points(lm[rows]), feats.keypoints_px[matches.i[rows]])
    err = err / keypoint_sigmas(feats)[matches.i[rows]]
    good = err <= conf.max_reprojection_px
    rows, err = rows[good], err[good]
    rows = rows[_first_unique([matches.i[rows], lm[rows]], np.argsort(err, kind="stable"))]
    kmap.add_observations(kind, zip(lm[rows].tolist(), [kf_id] * len(rows),
                                    matches.i[rows].tolist(), strict=True))
    return lm[rows]


def _extend_into_neighbours(kmap: KeyframeMap, kf_id: int, kind: str, matches: _Matches,
                            conf: TriangulationConf) -> IntArray:
    """Attach free keypoints of the neighbours to the new keyframe's landmarks (also those
    that arrived with it) that reproject within the threshold; returns the landmark ids."""
    state = kmap.snapshot()
    feats = state.keyframe(kf_id).features[kind]
    lm = feats.landmark_ids[matches.i]
    triples: list[tuple[int, int, int]] = []
    for n in np.unique(matches.other[lm >= 0]):
        other = state.keyframes[int(n)]
        of = other.features[kind]
        rows = matches.rows_of(int(n))
        rows = rows[(lm[rows] >= 0) & (of.landmark_ids[matches.j[rows]] < 0)
                    & ~np.isin(lm[rows], of.landmark_ids)]
        err = _pixel_errors(other, feats.points_world[matches.i[rows]],
                            of.keypoints_px[matches.j[rows]])
        rows = rows[err <= conf.max_reprojection_px * keypoint_sigmas(of)[matches.j[rows]]]
        triples += zip(lm[rows].tolist(), [int(n)] * len(rows), matches.j[rows].tolist(),
                       strict=True)
    kmap.add_observations(kind, triples)
    return np.array([t[0] for t in triples], np.int64)


def _free_rows(state: MapState, kf_id: int, kind: str, matches: _Matches) -> IntArray:
    """Rows whose keypoints have no landmark on either side."""
    feats = state.keyframe(kf_id).features[kind]
    return np.flatnonzero((feats.landmark_ids[matches.i] < 0)
                          & (_landmark_of(state, matches, kind) < 0))


def _views_of_rows(state: MapState, kf_id: int, kind: str, matches: _Matches, rows: IntArray
                   ) -> tuple[list[ViewObservations], list[IntArray], IntArray]:
    """Views of the free matches grouped by keypoint of the new keyframe: the views (new
    keyframe first), the keypoint index of each observation per view, and the new keyframe's
    keypoint of each point."""
    kf = state.keyframe(kf_id)
    kp_index, point_of_row = np.unique(matches.i[rows], return_inverse=True)
    views = [_view(kf, kind, np.arange(len(kp_index)), kp_index)]
    keypoints = [kp_index]
    for n in np.unique(matches.other[rows]):
        sel = matches.other[rows] == n
        j = matches.j[rows][sel]
        views.append(_view(state.keyframes[int(n)], kind, point_of_row[sel], j))
        keypoints.append(j)
    return views, keypoints, kp_index


def _view(keyframe: Keyframe, kind: str, point_index: IntArray, keypoints: IntArray
          ) -> ViewObservations:
    """Observations by ``keyframe``'s ``kind`` keypoints (K,) of points ``point_index`` (K,)."""
    feats = keyframe.features[kind]
    return ViewObservations(keyframe.camera, invert(keyframe.world_from_cam), point_index,
                            feats.keypoints_px[keypoints], keypoint_sigmas(feats)[keypoints])


def _observation_lists(kf_ids: Sequence[int], views: Sequence[ViewObservations],
                       keypoints: Sequence[IntArray], kept: Sequence[npt.NDArray[np.bool_]],
                       points: IntArray) -> list[list[tuple[int, int]]]:
    """``(keyframe id, keypoint index)`` observations of each point in ``points`` (sorted)."""
    pt = np.concatenate([v.point_index[k] for v, k in zip(views, kept, strict=True)])
    kf = np.concatenate([np.full(int(k.sum()), i, np.int64)
                         for i, k in zip(kf_ids, kept, strict=True)])
    kp = np.concatenate([kpi[k] for kpi, k in zip(keypoints, kept, strict=True)])
    order = np.argsort(pt, kind="stable")
    pt, kf, kp = pt[order], kf[order], kp[order]
    bounds = np.searchsorted(pt, points, side="left"), np.searchsorted(pt, points, side="right")
    pairs = list(zip(kf.tolist(), kp.tolist(), strict=True))
    return [pairs[a:b] for a, b in zip(bounds[0].tolist(), bounds[1].tolist(), strict=True)]


def _create_by_triangulation(kmap: KeyframeMap, kf_id: int, kind: str, matches: _Matches,
                             conf: TriangulationConf, stats: TriangulationStats) -> None:
    state = kmap.snapshot()
    rows = _free_rows(state, kf_id, kind, matches)
    if len(rows) == 0:
        return
    views, keypoints, kp_index = _views_of_rows(state, kf_id, kind, matches, rows)
    result = triangulate_tracks(views, len(kp_index), conf)
    for status in TrackStatus:
        count = int(np.sum(result.status == status))
        if status is not TrackStatus.OK and count:
            stats.rejected[status.name.lower()] = stats.rejected.get(status.name.lower(), 0) + count
    accepted = np.flatnonzero(result.accepted)
    kf_ids = [kf_id] + [int(n) for n in np.unique(matches.other[rows])]
    obs = _observation_lists(kf_ids, views, keypoints, result.kept, accepted)
    stats.created += len(kmap.add_landmarks(kind, result.points_world[accepted], obs,
                                            depth_sigmas_m=result.depth_sigmas_m[accepted]))


def _create_from_depth(kmap: KeyframeMap, kf_id: int, kind: str, matches: _Matches,
                       conf: TriangulationConf, stats: TriangulationStats) -> None:
    """Landmarks at the depth of the new keyframe's free keypoints, also observed by the
    neighbours' free matched keypoints where they reproject within the threshold."""
    state = kmap.snapshot()
    kf = state.keyframe(kf_id)
    indices, points = landmarks_from_depth(kf, kind, conf)
    if len(indices) == 0:
        return
    rows = _free_rows(state, kf_id, kind, matches)
    rows = rows[np.isin(matches.i[rows], indices)]
    pos = np.searchsorted(indices, matches.i[rows])
    views = [_view(kf, kind, np.arange(len(indices)), indices)]
    keypoints, kf_ids = [indices], [kf_id]
    for n in np.unique(matches.other[rows]):
        sel = matches.other[rows] == n
        j = matches.j[rows][sel]
        views.append(_view(state.keyframes[int(n)], kind, pos[sel], j))
        keypoints.append(j)
        kf_ids.append(int(n))
    errors = reprojection_errors(points, views)
    kept = [np.ones(len(indices), bool)] + [e <= conf.max_reprojection_px * v.sigmas
                                            for e, v in zip(errors[1:], views[1:], strict=True)]
    obs = _observation_lists(kf_ids, views, keypoints, kept, np.arange(len(indices)))
    stats.from_depth += len(kmap.add_landmarks(kind, points, obs))


def _refine_tracks(kmap: KeyframeMap, kind: str, landmark_ids: IntArray, conf: TriangulationConf
                   ) -> int:
    """Re-refine landmarks over all their observations; a refined point replaces the old one
    only if it stays within the reprojection threshold and depth range in every view.
    Landmarks stated exact (depth sigma 0: lifted from a depth map) keep their point: the
    reprojection error cannot say where along nearly parallel rays a point lies, so a
    measured point seen again from a few millimetres or centimetres away would slide along
    its ray to wherever its keypoints' noise puts it (on a camera panning in place, 43 % of
    a depth map's landmarks ended more than 5 cm off, some metres), and a query seen from
    elsewhere would find it there. Returns the number of landmarks moved."""
    state = kmap.snapshot()
    ids = np.unique(landmark_ids)
    ids = ids[state.landmarks.contains(ids)]
    if len(ids) == 0:
        return 0
    observers = sorted({o[0] for i in ids.tolist() for o in state.landmarks[i].observations
                        if o[1] == kind})
    views = []
    for k in observers:
        feats = state.keyframes[k].features[kind]
        idx = np.flatnonzero(np.isin(feats.landmark_ids, ids))
        views.append(_view(state.keyframes[k], kind, np.searchsorted(ids, feats.landmark_ids[idx]),
                           idx))
    old = state.landmark_points(ids)
    new = refine_points(old, views, iterations=conf.refine_iterations, min_depth=conf.min_depth_m)
    bad_depth, bad_reproj = observation_faults(new, views, conf)
    good = np.asarray(np.isfinite(new).all(axis=1), dtype=bool)
    for v, d, r in zip(views, bad_depth, bad_reproj, strict=True):
        good[v.point_index[d | r]] = False
    good &= np.linalg.norm(new - old, axis=1) > 0
    good &= state.landmark_sigmas(ids) > 0      # a measured point is not moved by keypoints
    kmap.move_landmarks(ids[good], new[good])
    return int(good.sum())


def triangulate_keyframe(kmap: KeyframeMap, kf_id: int, neighbour_ids: Iterable[int], kind: str,
                         conf: TriangulationConf | None = None, *, use_depth: bool = True
                         ) -> TriangulationStats:
    """Landmarks of keyframe ``kf_id`` (already in ``kmap``) for features ``kind``, matching
    against ``neighbour_ids`` only: matches to existing landmarks extend their tracks (in both
    directions); when the keyframe has a depth map and ``use_depth``, every free keypoint with a
    valid depth becomes a landmark; the remaining free matches are triangulated; extended
    tracks are re-refined."""
    conf = conf or TriangulationConf()
    stats = TriangulationStats()
    state = kmap.snapshot()
    kf = state.keyframe(kf_id)
    if kind not in kf.features or len(kf.features[kind]) == 0:
        return stats
    matches = _match_neighbours(state, kf, neighbour_ids, kind, conf, stats)
    extended = _extend_into_keyframe(kmap, kf_id, kind, matches, conf)
    extended_out = _extend_into_neighbours(kmap, kf_id, kind, matches, conf)
    stats.extended = len(extended) + len(extended_out)
    if use_depth and kf.depth is not None:
        _create_from_depth(kmap, kf_id, kind, matches, conf, stats)
    # Keypoints the depth map does not cover (holes, range, discontinuities) are triangulated.
    _create_by_triangulation(kmap, kf_id, kind, matches, conf, stats)
    if conf.refine_tracks:
        stats.refined = _refine_tracks(kmap, kind, np.concatenate([extended, extended_out]), conf)
    return stats
