"""Guided matching (search by projection, as ORB-SLAM's relocalization does): once a first pose
exists, project the landmarks of the local map into the query and match each only against the
query keypoints in a window around its projection, where blur, exposure change or a crowd of
similar descriptors no longer hide the right match from a global ratio test."""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from ...core.cameras import Camera
from ...core.frame import Features, is_binary_descriptor
from ...core.geometry import invert, transform_points
from .guided_kernels import compiled
from .keypoint_grid import window_neighbours
from .projection import project_cam

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Query keypoints examined around each projection (the window rarely holds more).
_WINDOW_NEIGHBOURS = 8
#: Descriptor pairs sampled to estimate the distance distribution of unrelated features.
_BACKGROUND_SAMPLE = 256

#: The KD-tree of each keypoint set's positions, built on first use: one query's keypoints
#: are searched by guided matching, by the support of each hypothesis and by the repetition
#: search, from every candidate group and fallback step with that feature kind (features
#: are frozen, so the tree stays theirs; it goes when they do).
_TREES: weakref.WeakKeyDictionary[Features, cKDTree] = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class GuidedConf:
    """Search-by-projection settings."""

    #: Window radius as a multiple of the pose's inlier threshold: the first pose reprojects
    #: its inliers within one threshold, landmarks elsewhere in the image within about two.
    window_factor: float = 2.0
    #: Ratio of the best to the second-best descriptor distance inside the window (ORB-SLAM's
    #: search by projection uses 0.9: the window already excludes most confusers).
    window_ratio: float = 0.9
    #: A match must also be closer than this quantile of the distances between unrelated
    #: descriptors (estimated on each query): a chance pair passes with at most this
    #: probability, however empty the window.
    background_quantile: float = 0.01
    #: Keyframes near the first pose whose landmarks are projected (besides the candidates).
    local_keyframes: int = 10
    #: Largest angle between a local keyframe's optical axis and the first pose's, degrees.
    max_view_angle_deg: float = 60.0


def project_into(camera: Camera, world_from_cam: Array, points_world: Array
                 ) -> tuple[Array, npt.NDArray[np.bool_]]:
    """(N, 2) pixels of world points seen from ``world_from_cam`` and the mask of those in
    front of the camera and inside the image."""
    points_cam = transform_points(invert(world_from_cam), points_world)
    with np.errstate(invalid="ignore", divide="ignore"):
        px = project_cam(camera, points_cam)
        width, height = camera.size
        visible = ((points_cam[:, 2] > 0) & np.isfinite(px).all(axis=1)
                   & (px[:, 0] >= -0.5) & (px[:, 0] <= width - 0.5)
                   & (px[:, 1] >= -0.5) & (px[:, 1] <= height - 0.5))
    return px, visible


def background_distance(query_desc: npt.NDArray[Any], map_desc: npt.NDArray[Any],
                        quantile: float, rng_seed: int = 0) -> float:
    """The ``quantile`` of distances between query and map descriptors drawn at random (almost
    all unrelated pairs): a match closer than this is unlikely to be chance. Binary
    descriptors' distances are counted into a histogram where numba is installed
    (:mod:`.guided_kernels`): the same quantile to rounding, and the same verdicts, since a
    Hamming distance is an integer and the quantile lies either on one or strictly between
    two."""
    if len(query_desc) == 0 or len(map_desc) == 0:
        return 0.0
    rng = np.random.default_rng(rng_seed)
    a = query_desc[rng.integers(0, len(query_desc), _BACKGROUND_SAMPLE)]
    b = map_desc[rng.integers(0, len(map_desc), _BACKGROUND_SAMPLE)]
    kernels = compiled()
    if kernels is not None and _packs_into_words(a) and _same_kind(a, b):
        counts = np.zeros(8 * a.shape[1] + 1, np.int64)
        kernels.hamming_histogram(_words(a), _words(b), counts)
        return _histogram_quantile(counts, quantile)
    fa, fb = _as_float(a), _as_float(b)
    d2 = (fa * fa).sum(1)[:, None] + (fb * fb).sum(1)[None, :] - 2.0 * fa @ fb.T
    return float(np.quantile(_distance(np.maximum(d2, 0.0), query_desc), quantile))


def _histogram_quantile(counts: npt.NDArray[np.int64], quantile: float) -> float:
    """``np.quantile`` (its default, linear interpolation) of the values 0, 1, 2, ... held
    ``counts`` times each: between the order statistics at ``quantile * (n - 1)``."""
    n = int(counts.sum())
    position = quantile * (n - 1)
    below = int(np.floor(position))
    cumulative = np.cumsum(counts)
    lo, hi = (int(np.searchsorted(cumulative, i, side="right"))
              for i in (below, min(below + 1, n - 1)))
    return float(lo + (hi - lo) * (position - below))


def search_by_projection(feats: Features, camera: Camera, world_from_cam: Array,
                         map_desc: npt.NDArray[Any], points_world: Array, radius_px: float,
                         conf: GuidedConf) -> tuple[IntArray, IntArray]:
    """Matches of map landmarks (descriptors (L, D), points (L, 3)) to query keypoints within
    ``radius_px`` of their projection under ``world_from_cam``: (M,) query keypoint indices
    and (M,) landmark rows, one landmark per keypoint and one keypoint per landmark."""
    empty = np.zeros(0, np.int64)
    if len(feats) < 2 or len(points_world) == 0:
        return empty, empty
    px, visible = project_into(camera, world_from_cam, points_world)
    rows = np.flatnonzero(visible)
    k = min(_WINDOW_NEIGHBOURS, len(feats))
    near = window_neighbours(feats.keypoints_px, px[rows], k, radius_px,
                             lambda: keypoint_tree(feats))
    best, second, first = _window_best(feats.descriptors, map_desc[rows], near)
    limit = background_distance(feats.descriptors, map_desc, conf.background_quantile)
    ok = np.isfinite(best) & (best < conf.window_ratio * second) & (best < limit)
    query_idx = near[np.flatnonzero(ok), first[ok]]
    return _one_to_one(query_idx, rows[ok].astype(np.int64), best[ok])


def keypoint_tree(feats: Features) -> cKDTree:
    """The KD-tree of ``feats.keypoints_px`` (built once per features, see :data:`_TREES`)."""
    tree = _TREES.get(feats)
    if tree is None:
        tree = cKDTree(feats.keypoints_px)
        _TREES[feats] = tree
    return tree


def _window_best(query_desc: npt.NDArray[Any], landmark_desc: npt.NDArray[Any], near: IntArray
                 ) -> tuple[Array, Array, IntArray]:
    """For each landmark (row of ``landmark_desc``), the descriptor distances to its window
    keypoints ``near`` (L, K) (indices ``>= len(query_desc)``: empty slots): (L,) the
    smallest, (L,) the next smallest (inf if none) and (L,) the slot of the smallest, the
    first of equal ones (-1 if none). One compiled pass where numba is installed and both
    sides are ORB's words or uint8 SIFT (:mod:`.guided_kernels`, the same values: exact
    integer distances, the same float32 roots); else array operations on the (L, K)
    distances (float SIFT descriptors, a map holding another dtype than the query)."""
    rows, k = near.shape
    kernels = compiled()
    if kernels is not None and _same_kind(query_desc, landmark_desc) and (
            _packs_into_words(query_desc) or _is_uint8_sift(query_desc)):
        first = np.empty(rows, np.int64)
        if _packs_into_words(query_desc):
            best, second = np.empty(rows), np.empty(rows)
            kernels.window_best_hamming(_words(query_desc), _words(landmark_desc), near, best,
                                        second, first)
        else:
            best, second = np.empty(rows, np.float32), np.empty(rows, np.float32)
            kernels.window_best_l2(np.ascontiguousarray(query_desc),
                                   np.ascontiguousarray(landmark_desc), near, best, second,
                                   first)
        return best, second, first
    in_window = near < len(query_desc)
    dist = _window_distances(query_desc, landmark_desc, np.where(in_window, near, 0))
    dist[~in_window] = np.inf
    order = np.argsort(dist, axis=1, kind="stable")
    best = np.take_along_axis(dist, order[:, :1], axis=1)[:, 0]
    second = (np.take_along_axis(dist, order[:, 1:2], axis=1)[:, 0] if k > 1
              else np.full(rows, np.inf))
    return best, second, np.where(np.isfinite(best), order[:, 0], -1)


def _packs_into_words(desc: npt.NDArray[Any]) -> bool:
    """Binary descriptors whose bytes make whole 64-bit words (ORB's 32)."""
    return is_binary_descriptor(desc) and desc.shape[1] % 8 == 0


def _same_kind(a: npt.NDArray[Any], b: npt.NDArray[Any]) -> bool:
    """Descriptors of one dtype and width (what the compiled passes take)."""
    return a.dtype == b.dtype and a.shape[1:] == b.shape[1:]


def _is_uint8_sift(desc: npt.NDArray[Any]) -> bool:
    return desc.dtype == np.uint8 and not is_binary_descriptor(desc)


def _words(desc: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint64]:
    """(N, bytes / 8) 64-bit words of binary descriptors (a view where contiguous)."""
    return np.ascontiguousarray(desc).view(np.uint64)


def _window_distances(query_desc: npt.NDArray[Any], landmark_desc: npt.NDArray[Any],
                      near: IntArray) -> Array:
    """(L, K) descriptor distance of each landmark to its K window keypoints."""
    if _packs_into_words(query_desc):
        # Binary (ORB; SIFT is uint8 too, but compared by L2): popcount of XOR on 64-bit
        # words, the Hamming distance exactly, without the (L, K, 8 x bytes) float array of
        # unpacked bits (80 MB for 10k landmarks with ORB).
        words = _words(query_desc)[near]                  # (L, K, W)
        own = _words(landmark_desc)[:, None, :]           # (L, 1, W)
        return np.bitwise_count(words ^ own).sum(axis=2, dtype=np.int64).astype(np.float64)
    a = _as_float(query_desc)[near]                       # (L, K, D)
    b = _as_float(landmark_desc)[:, None, :]              # (L, 1, D)
    d2 = np.einsum("lkd,lkd->lk", a - b, a - b)
    return _distance(d2, query_desc)


def _one_to_one(query_idx: IntArray, rows: IntArray, dist: Array) -> tuple[IntArray, IntArray]:
    """Keep, for each query keypoint, its closest landmark."""
    order = np.lexsort((dist, query_idx))
    _, first = np.unique(query_idx[order], return_index=True)
    keep = np.sort(order[first])
    return query_idx[keep], rows[keep]


def _as_float(desc: npt.NDArray[Any]) -> npt.NDArray[np.float32]:
    """Descriptors as float vectors; binary ones as bits (squared L2 = Hamming distance)."""
    if is_binary_descriptor(desc):
        return np.unpackbits(desc, axis=-1).astype(np.float32)
    return desc.astype(np.float32)


def _distance(d2: Array, desc: npt.NDArray[Any]) -> Array:
    """Squared L2 on bits is the Hamming distance; on float descriptors take the root."""
    return np.asarray(d2, np.float64) if is_binary_descriptor(desc) else np.sqrt(d2)
