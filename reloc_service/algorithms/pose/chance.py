"""The chance that a correspondence agrees with a wrong pose, estimated on the data (the
a-contrario verification's ``p``, see :func:`~reloc_service.algorithms.pose.base.log10_false_alarms`):
correspondences bunched in a few places agree by chance far more often than the uniform
``pi t^2 / area`` says."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .kernels import compiled

Array = npt.NDArray[np.float64]


def chance_agreement(projected_px: Array, px: Array, threshold_px: float,
                     image_size: tuple[int, int], *, max_points: int = 200) -> float:
    """Probability that a correspondence agrees within ``threshold_px`` by chance, estimated
    on the data: the share of mismatched pairings (point j projected at ``projected_px[j]``
    against keypoint ``px[i]``, i != j) that agree, at least the uniform ``pi t^2 / area``.
    At most ``max_points`` evenly chosen correspondences are paired (a fixed cost)."""
    width, height = image_size
    uniform = float(np.pi * threshold_px**2 / (width * height))
    n = len(px)
    if n < 2:
        return uniform
    if n <= max_points:  # every correspondence (what the even choice below picks then)
        m, agree = n, _pairs_within(projected_px, px, threshold_px)
    else:
        idx = np.unique(np.linspace(0, n - 1, max_points).astype(np.int64))
        m = len(idx)
        agree = _pairs_within(projected_px[idx], px[idx], threshold_px)
    return max(uniform, float(agree) / (m * (m - 1)))


def _pairs_within(projected_px: Array, px: Array, threshold_px: float) -> int:
    """Number of pairs ``j != i`` with ``|projected_px[j] - px[i]| < threshold_px``: only
    the pairs whose x coordinates lie within twice the threshold (``px`` sorted by x, a
    superset of those that agree) are measured, with the same arithmetic as the full (m, m)
    table (per axis difference, squares summed), so the count is the table's. Compiled
    where numba is installed (:mod:`.kernels`, the same count)."""
    kernels = compiled()
    if kernels is not None:
        return int(kernels.pairs_within(np.ascontiguousarray(projected_px, np.float64),
                                        np.ascontiguousarray(px, np.float64),
                                        float(threshold_px), float(threshold_px)**2))
    order = np.argsort(px[:, 0], kind="stable")
    xs = px[order, 0]
    lo = np.searchsorted(xs, projected_px[:, 0] - 2.0 * threshold_px, side="left")
    hi = np.searchsorted(xs, projected_px[:, 0] + 2.0 * threshold_px, side="right")
    counts = np.maximum(hi - lo, 0)
    j = np.repeat(np.arange(len(projected_px)), counts)
    first = np.repeat(lo - (np.cumsum(counts) - counts), counts)  # lo[j] - start of j's run
    i = order[first + np.arange(len(j))]
    dx = projected_px[j, 0] - px[i, 0]  # per axis: the full table's element arithmetic
    dy = projected_px[j, 1] - px[i, 1]
    d2 = dx * dx + dy * dy
    return int(np.count_nonzero((d2 < threshold_px**2) & (i != j)))
