"""The window test of localization with a prior: for each landmark, every query keypoint
inside its chi-square gate (``d^T S^-1 d <= gate``, :mod:`.prior_windows`) and the
smallest and next smallest descriptor distance among them.

A prior of a few degrees makes gates of a hundred pixels, which hold tens of keypoints
each: every one of them is a candidate, so the ratio test sees all the confusers of its
window. Two paths give the same values: array operations on the candidate pairs (a k-d tree
lists the pairs within the largest gate's radius, then the gate, the distances and a sort
by landmark), and, where numba is installed (the ``[jit]`` extra) and the descriptors are
ORB's, one compiled pass per landmark over the query keypoints inside its gate's bounding
box (the keypoints kept in horizontal bands, sorted by x inside each) that tests the gate
before it computes a Hamming distance. Ties go to the lowest keypoint index in both.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from ...core.features import descriptor_distance
from ...core.frame import is_binary_descriptor
from ...core.hamming import _popcount64
from ...core.numeric import numba_or_none

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def gated_best(keypoints_px: Array, query_desc: npt.NDArray[Any], px: Array, inv_cov: Array,
               radius_px: Array, landmark_desc: npt.NDArray[Any], gate_chi2: float
               ) -> tuple[Array, Array, IntArray]:
    """For each of L landmarks (projections ``px`` (L, 2), inverse projection covariances
    ``inv_cov`` (L, 2, 2), gate radii ``radius_px`` (L,), descriptors ``landmark_desc``),
    among the query keypoints (``keypoints_px`` (N, 2), ``query_desc``) inside its gate:
    (L,) the smallest descriptor distance (inf if none), (L,) the next smallest (inf if
    none) and (L,) the index of the keypoint of the smallest (-1 if none)."""
    if len(px) == 0 or len(keypoints_px) == 0:
        return (np.full(len(px), np.inf), np.full(len(px), np.inf),
                np.full(len(px), -1, np.int64))
    kernel = _compiled()
    if kernel is not None and _are_orb_words(query_desc, landmark_desc):
        best, second = np.empty(len(px)), np.empty(len(px))
        index = np.empty(len(px), np.int64)
        half_x, half_y = _gate_half_extents(inv_cov, radius_px, gate_chi2)
        bands = _KeypointBands.of(np.ascontiguousarray(keypoints_px, np.float64), half_y)
        kernel(bands.keypoints_px, bands.order, bands.x_sorted, bands.starts, bands.y0,
               bands.height, _words(query_desc), np.ascontiguousarray(px, np.float64),
               _gate_coefficients(inv_cov), half_x, half_y, float(gate_chi2),
               _words(landmark_desc), best, second, index)
        return best, second, index
    return _gated_best_numpy(keypoints_px, query_desc, px, inv_cov, radius_px, landmark_desc,
                             gate_chi2)


def _gated_best_numpy(keypoints_px: Array, query_desc: npt.NDArray[Any], px: Array,
                      inv_cov: Array, radius_px: Array, landmark_desc: npt.NDArray[Any],
                      gate_chi2: float) -> tuple[Array, Array, IntArray]:
    """:func:`gated_best` by array operations on the (landmark, keypoint) pairs."""
    n = len(px)
    best, second = np.full(n, np.inf), np.full(n, np.inf)
    index = np.full(n, -1, np.int64)
    lm, kp = _gated_pairs(keypoints_px, px, inv_cov, radius_px, gate_chi2)
    if len(lm) == 0:
        return best, second, index
    dist = descriptor_distance(query_desc[kp], landmark_desc[lm])
    order = np.lexsort((kp, dist, lm))          # by landmark, then distance, then keypoint
    lm, kp, dist = lm[order], kp[order], dist[order]
    starts = np.flatnonzero(np.r_[True, lm[1:] != lm[:-1]])
    best[lm[starts]], index[lm[starts]] = dist[starts], kp[starts]
    follows = starts + 1
    has_second = follows < len(lm)
    has_second[has_second] = lm[follows[has_second]] == lm[starts[has_second]]
    second[lm[starts[has_second]]] = dist[follows[has_second]]
    return best, second, index


def _gated_pairs(keypoints_px: Array, px: Array, inv_cov: Array, radius_px: Array,
                 gate_chi2: float) -> tuple[IntArray, IntArray]:
    """(P,) landmark and (P,) keypoint indices of the pairs inside the landmarks' gates,
    by landmark. The landmarks are taken in classes of radius within a factor of two, each
    class's pairs within its largest radius listed by a k-d tree (a gate lies inside the
    circle of its half major axis; a relative margin of 1e-9 keeps rounding from dropping
    a pair on its boundary), then each landmark's own gate."""
    finite = np.flatnonzero(np.isfinite(radius_px))
    if len(finite) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    tree = cKDTree(keypoints_px)
    octave = np.floor(np.log2(np.maximum(radius_px[finite], 1e-3))).astype(np.int64)
    lm_parts, kp_parts = [], []
    for value in np.unique(octave):
        rows = finite[octave == value]
        bound = float(radius_px[rows].max()) * (1.0 + 1e-9) + 1e-9
        pairs = cKDTree(px[rows]).sparse_distance_matrix(tree, bound, output_type="ndarray")
        lm_parts.append(rows[pairs["i"].astype(np.int64)])
        kp_parts.append(pairs["j"].astype(np.int64))
    lm, kp = np.concatenate(lm_parts), np.concatenate(kp_parts)
    d = keypoints_px[kp] - px[lm]
    inv = inv_cov[lm]
    m2 = (inv[:, 0, 0] * d[:, 0] ** 2 + 2.0 * inv[:, 0, 1] * d[:, 0] * d[:, 1]
          + inv[:, 1, 1] * d[:, 1] ** 2)
    keep = m2 <= gate_chi2
    return lm[keep], kp[keep]


def _are_orb_words(query_desc: npt.NDArray[Any], landmark_desc: npt.NDArray[Any]) -> bool:
    """Binary descriptors of one width that make whole 64-bit words (what the kernel takes)."""
    return (is_binary_descriptor(query_desc) and query_desc.dtype == landmark_desc.dtype
            and query_desc.shape[1:] == landmark_desc.shape[1:] and query_desc.shape[1] % 8 == 0)


def _words(desc: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint64]:
    return np.ascontiguousarray(desc).view(np.uint64)


def _gate_coefficients(inv_cov: Array) -> Array:
    """(L, 3) ``a, b, c`` of each gate's quadratic form ``a dx^2 + 2 b dx dy + c dy^2``."""
    return np.ascontiguousarray(np.stack([inv_cov[:, 0, 0], inv_cov[:, 0, 1], inv_cov[:, 1, 1]],
                                         axis=1), np.float64)


#: Relative and absolute margins by which a gate's bounding box is widened: rounding in
#: the box's computation must never drop a keypoint the gate test itself would keep.
_BOX_MARGIN_REL, _BOX_MARGIN_ABS = 1e-6, 1e-9
#: Below this ``det / (a c)`` of a gate's quadratic form (a correlation of the two pixel
#: axes above 0.9999995) the axis extents lose digits to cancellation, and the gate's half
#: major axis bounds it instead.
_NEAR_SINGULAR = 1e-6


def _gate_half_extents(inv_cov: Array, radius_px: Array, gate_chi2: float
                       ) -> tuple[Array, Array]:
    """(L,) half widths and (L,) half heights of the axis-aligned boxes around the gates
    ``d^T S^-1 d <= gate_chi2``: ``sqrt(gate_chi2 S_xx)`` and ``sqrt(gate_chi2 S_yy)``
    (``S`` the inverse of ``inv_cov``), widened by the box margins and at most the gate's
    half major axis ``radius_px`` (with the same margins as the bound it was); -1 where the
    radius is not finite (no candidate)."""
    a, b, c = inv_cov[:, 0, 0], inv_cov[:, 0, 1], inv_cov[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        det = a * c - b * b
        sound = (det > _NEAR_SINGULAR * a * c) & (a > 0) & (c > 0)
        half_x = np.sqrt(gate_chi2 * c / det)
        half_y = np.sqrt(gate_chi2 * a / det)
    finite = np.isfinite(radius_px)
    bound = np.where(finite, radius_px, 0.0) * (1.0 + 1e-9) + 1e-9
    out = []
    for half in (half_x, half_y):
        half = np.where(sound & np.isfinite(half),
                        half * (1.0 + _BOX_MARGIN_REL) + _BOX_MARGIN_ABS, bound)
        out.append(np.ascontiguousarray(np.where(finite, np.minimum(half, bound), -1.0)))
    return out[0], out[1]


class _KeypointBands:
    """Query keypoints in horizontal bands of one height, sorted by x inside each band: a
    gate's candidates are the keypoints of the bands its box spans, each band's run of x
    within the box found by bisection, so a gate tests the keypoints of its box rather than
    those of the whole image's rows it spans. The band height is half the median gate's
    half height: a box then spans a few bands, and at most one band's height of keypoints
    above and below it is tested in vain. It changes the cost, never the candidates."""

    def __init__(self, keypoints_px: Array, order: npt.NDArray[np.int64], x_sorted: Array,
                 starts: npt.NDArray[np.int64], y0: float, height: float) -> None:
        self.keypoints_px, self.order, self.x_sorted = keypoints_px, order, x_sorted
        self.starts, self.y0, self.height = starts, y0, height

    @classmethod
    def of(cls, keypoints_px: Array, half_y: Array) -> _KeypointBands:
        """The bands of (N, 2) ``keypoints_px`` for gates of half heights ``half_y`` (L,)."""
        spans = half_y[half_y > 0]
        height = max(float(np.median(spans)) / 2.0 if len(spans) else 1.0, 1.0)
        y0 = float(keypoints_px[:, 1].min())
        band = np.floor((keypoints_px[:, 1] - y0) / height).astype(np.int64)
        order = np.lexsort((keypoints_px[:, 0], band)).astype(np.int64)
        starts = np.searchsorted(band[order], np.arange(int(band.max()) + 2)).astype(np.int64)
        return cls(keypoints_px, order, np.ascontiguousarray(keypoints_px[order, 0]), starts,
                   y0, height)


def _gated_best_hamming(keypoints_px: Array, order: npt.NDArray[np.int64], x_sorted: Array,
                        starts: npt.NDArray[np.int64], y0: float, height: float,
                        query_words: npt.NDArray[np.uint64], px: Array, coefficients: Array,
                        half_x: Array, half_y: Array, gate_chi2: float,
                        landmark_words: npt.NDArray[np.uint64], best: Array, second: Array,
                        index: npt.NDArray[np.int64]) -> None:
    """The compiled pass of :func:`gated_best` (ORB): per landmark, the keypoints inside its
    gate's box (:class:`_KeypointBands`: ``order`` keypoint indices by band then x,
    ``x_sorted`` their x, ``starts`` each band's first position), each one's gate test, and
    a Hamming distance only for those inside. Of equal distances the lowest keypoint index
    is the best, whatever order the keypoints are visited in."""
    last_band = starts.shape[0] - 2
    for r in range(px.shape[0]):
        b, s, f = math.inf, math.inf, -1
        a, c2, c = coefficients[r, 0], coefficients[r, 1], coefficients[r, 2]
        x, y = px[r, 0], px[r, 1]
        if half_y[r] >= 0:
            first = max(int(math.floor((y - half_y[r] - y0) / height)), 0)
            final = min(int(math.floor((y + half_y[r] - y0) / height)), last_band)
            for band in range(first, final + 1):
                lo0, hi0 = starts[band], starts[band + 1]
                if lo0 == hi0:
                    continue
                xs = x_sorted[lo0:hi0]
                lo = lo0 + np.searchsorted(xs, x - half_x[r], side="left")
                hi = lo0 + np.searchsorted(xs, x + half_x[r], side="right")
                for k in range(lo, hi):
                    q = order[k]
                    dx, dy = keypoints_px[q, 0] - x, keypoints_px[q, 1] - y
                    if a * dx * dx + 2.0 * c2 * dx * dy + c * dy * dy > gate_chi2:
                        continue
                    dist = 0
                    for t in range(query_words.shape[1]):
                        dist += _popcount64(query_words[q, t] ^ landmark_words[r, t])
                    if dist < b or (dist == b and q < f):
                        b, s, f = float(dist), b, q
                    elif dist < s:
                        s = float(dist)
        best[r], second[r], index[r] = b, s, f


@functools.cache
def _compiled() -> Any:
    """The compiled :func:`_gated_best_hamming` (cached on disk by numba), or None where
    numba is not installed."""
    global _popcount64
    numba = numba_or_none()
    if numba is None:
        return None
    helper: Any = numba.njit(cache=True, nogil=True, inline="always")
    _popcount64 = helper(getattr(_popcount64, "py_func", _popcount64))
    jit: Any = numba.njit(cache=True, nogil=True)
    return jit(_gated_best_hamming)
