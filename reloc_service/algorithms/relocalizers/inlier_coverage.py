"""Where an estimate's inliers lie: the image cells they touch, the share of the image their
convex hull spans, and whether their world points lie on one plane (the coverage tests of
:func:`~.base.verify`)."""

from __future__ import annotations

import functools

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial import ConvexHull, QhullError

from ...core import distributions as stats
from ..pose.base import PoseEstimate

Array = npt.NDArray[np.float64]


def inlier_cells(estimate: PoseEstimate, grid: int) -> int | None:
    """Number of cells of a ``grid`` x ``grid`` partition of the image holding an inlier; None
    when the estimate does not say where its inliers are."""
    if estimate.inlier_px is None or estimate.image_size is None or len(estimate.inlier_px) == 0:
        return None
    width, height = estimate.image_size
    col = np.clip((estimate.inlier_px[:, 0] + 0.5) * grid // width, 0, grid - 1).astype(int)
    row = np.clip((estimate.inlier_px[:, 1] + 0.5) * grid // height, 0, grid - 1).astype(int)
    return int(np.count_nonzero(np.bincount(row * grid + col, minlength=grid * grid)))


def inlier_spread(estimate: PoseEstimate) -> float | None:
    """Share of the image inside the inliers' convex hull, by OpenCV on float32 pixels (a
    few microseconds; within 1e-6 of :func:`planar_patch_fraction`'s hull at image
    coordinates), or None when the estimate does not say where its inliers are."""
    px, size = estimate.inlier_px, estimate.image_size
    if px is None or size is None or len(px) < 3:
        return None
    hull = cv2.convexHull(np.ascontiguousarray(px, np.float32).reshape(-1, 1, 2))
    return float(cv2.contourArea(hull)) / (size[0] * size[1])


def planar_patch_fraction(estimate: PoseEstimate) -> float | None:
    """Share of the image inside the inliers' convex hull when their world points lie on one
    plane (:func:`on_one_plane`); None when they do not, or when the estimate does not say.

    A pose whose whole support is one planar patch is fixed relative to that patch only: a
    print, a screen or a second copy of a poster elsewhere gives the same consensus, so such a
    patch must cover as much of the image as the coverage test asks of any support."""
    pts, sigmas, px = estimate.inlier_points_world, estimate.inlier_sigmas_m, estimate.inlier_px
    if pts is None or sigmas is None or px is None or estimate.image_size is None:
        return None
    if len(pts) < 4 or not on_one_plane(pts, sigmas):
        return None
    width, height = estimate.image_size
    try:
        area = ConvexHull(np.asarray(px, np.float64)).volume  # in 2-D, volume is the area
    except (QhullError, ValueError):  # collinear or repeated pixels: no area
        area = 0.0
    return float(area / (width * height))


def on_one_plane(points_world: Array, sigmas_m: Array, *, false_rejection: float = 0.01) -> bool:
    """Whether (N, 3) points with 1-sigma uncertainties (N,) are consistent with one plane:
    after a plane fit on the points within 3 sigma of it, no more of them lie beyond 3 sigma
    than Gaussian noise puts there (at most the binomial ``1 - false_rejection`` quantile of
    N draws with probability ``P(|z| > 3)``)."""
    pts = np.asarray(points_world, np.float64)
    sig = np.maximum(np.asarray(sigmas_m, np.float64), 1e-9)
    keep = np.ones(len(pts), bool)
    for _ in range(3):
        if keep.sum() < 3:
            return False
        refit, keep = keep, within_3_sigma_of_plane(pts, sig, keep)
        if np.array_equal(keep, refit):  # the same points would give the same plane again
            break
    return int(np.count_nonzero(~keep)) <= _max_outside_3_sigma(len(pts), false_rejection)


def within_3_sigma_of_plane(pts: Array, sig: Array, keep: npt.NDArray[np.bool_]
                            ) -> npt.NDArray[np.bool_]:
    """(N,) mask of the (N, 3) points within 3 of their 1-sigmas (N,) of the least-squares
    plane through the ``keep`` ones (its normal the smallest singular vector): one refit of
    :func:`on_one_plane`."""
    centre = pts[keep].mean(axis=0)
    normal = np.linalg.svd(pts[keep] - centre, full_matrices=False)[2][2]
    z = np.abs((pts - centre) @ normal) / sig
    return z < 3.0


@functools.lru_cache(maxsize=4096)
def _max_outside_3_sigma(n: int, false_rejection: float) -> float:
    """The binomial ``1 - false_rejection`` quantile of ``n`` draws with probability
    ``P(|z| > 3)``. Cached: ``scipy.stats`` spends about a millisecond per call checking its
    arguments, a tenth of the fast path's whole budget, and ``n`` (inliers) repeats."""
    tail = 2.0 * stats.norm.sf(3.0)
    return float(stats.binom.ppf(1.0 - false_rejection, n, tail))
