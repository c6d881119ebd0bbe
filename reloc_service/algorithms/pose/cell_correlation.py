"""How strongly reprojection errors are shared within an image cell, measured on a map's own
keyframes, and the variance inflation (design effect) it gives an estimate from few cells.

Residuals in one region of an image share part of their error (a blurred patch, landmarks
triangulated from the same few keyframes, local mis-association), so an estimate from ``m``
correspondences per cell varies more than the model's independent-noise covariance says.
The intrinsics test (:mod:`.intrinsics`) allows for that with the cluster-robust sandwich
over the occupied cells of a 4x4 grid, whose reference has ``G - 2`` degrees of freedom: on
the matches found without a pose, which lie in 3 to 5 cells, it can hardly reject anything.
The sharing can be measured instead, where the map's camera is right by definition: each
keyframe's landmarks re-triangulated without it (:mod:`.map_consistency`) and re-projected
into it leave residuals whose between-cell and within-cell variances (the one-way random
effects model, Searle, Casella & McCulloch 1992, 3.5: ``sigma_b^2 = (MSB - MSW) / n0``)
give the intra-cell correlation ``rho = sigma_b^2 / (sigma_b^2 + sigma_w^2)``. Before the
variance components are taken, the residuals are whitened by their keypoint sigmas and the
part a pose and ``theta`` explain (their 8 columns of the Jacobian) is projected out, as a
query's residuals are after its joint fit.

The keyframes near a pose give one ``rho`` each; their mean, with the one-sided upper
confidence bound of Student's t over the keyframes (:data:`CONFIDENCE`), is what the test
uses, so that a map whose keyframes disagree about the sharing states a larger one rather
than a lucky small one. An estimate from ``m_g`` correspondences in cell ``g`` has its
model variance inflated by Kish's design effect ``1 + (m - 1) rho`` with ``m = sum m_g^2 /
sum m_g`` (the size-weighted mean cell size; Kish 1965, 5.4): exact for a mean, an upper
bound for a regression coefficient whose regressor is less than fully shared within a cell.
The test then keeps the model's residual degrees of freedom.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import special

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: The one-sided confidence of the upper bound on ``rho`` over the keyframes (Student's t).
CONFIDENCE = 0.95

#: Fewest keyframes that give a ``rho`` for the map to state one (a t bound needs two
#: degrees of freedom to be finite in its variance).
MIN_KEYFRAMES = 3


@dataclass(frozen=True)
class CellComponents:
    """One keyframe's variance components of its whitened residuals over the grid cells
    (both coordinates pooled as two one-way layouts): between-cell and within-cell mean
    squares and ``n0``, the effective cell size of an unbalanced layout."""

    between_mean_square: float
    within_mean_square: float
    n0: float

    @property
    def rho(self) -> float:
        """The intra-cell correlation, ``sigma_b^2 / (sigma_b^2 + sigma_w^2)`` with the
        between-cell component ``(MSB - MSW) / n0`` truncated at zero."""
        between = max(0.0, (self.between_mean_square - self.within_mean_square) / self.n0)
        total = between + self.within_mean_square
        return between / total if total > 0 else 0.0


@dataclass(frozen=True)
class CellCorrelation:
    """The intra-cell correlation a map's keyframes show: the mean over ``keyframes`` of
    their estimates, its standard error and the upper bound at :data:`CONFIDENCE`."""

    rho: float
    standard_error: float
    upper: float
    keyframes: int


def grid_cells(px: Array, size: tuple[int, int], grid: int) -> IntArray:
    """(N,) the cell of a ``grid`` x ``grid`` partition of an image of ``size`` (width,
    height) each pixel of ``px`` (N, 2) lies in, row-major."""
    width, height = size
    col = np.clip(((px[:, 0] + 0.5) * grid // width).astype(np.int64), 0, grid - 1)
    row = np.clip(((px[:, 1] + 0.5) * grid // height).astype(np.int64), 0, grid - 1)
    return np.asarray(row * grid + col, np.int64)


def fitted_residuals(residuals: Array, jacobian: Array, weights: Array) -> Array:
    """(M, 2) residuals (M, 2) whitened by their weights (M,) (inverse variances) with the
    part the columns of ``jacobian`` (M, 2, P) explain projected out (least squares)."""
    root = np.sqrt(np.asarray(weights, np.float64))
    r = (residuals * root[:, None]).ravel()
    j = (jacobian * root[:, None, None]).reshape(len(r), -1)
    coef, *_ = np.linalg.lstsq(j, r, rcond=None)
    return np.asarray((r - j @ coef).reshape(-1, 2), np.float64)


def cell_components(residuals: Array, cells: IntArray) -> CellComponents | None:
    """The :class:`CellComponents` of residuals (M, 2) in ``cells`` (M,); None with fewer
    than two occupied cells or no within-cell degree of freedom."""
    _, index, counts = np.unique(cells, return_inverse=True, return_counts=True)
    g, n = len(counts), len(cells)
    if g < 2 or n - g < 1:
        return None
    sums = np.stack([np.bincount(index, weights=residuals[:, c], minlength=g)
                     for c in range(2)], axis=1)  # (G, 2)
    means = sums / counts[:, None]
    grand = residuals.mean(axis=0)
    between = float((counts[:, None] * (means - grand) ** 2).sum())
    within = float(((residuals - means[index]) ** 2).sum())
    n0 = (n - float((counts**2).sum()) / n) / (g - 1)
    return CellComponents(between / (2 * (g - 1)), within / (2 * (n - g)), n0)


def pooled_correlation(components: list[CellComponents]) -> CellCorrelation | None:
    """The map's :class:`CellCorrelation` from its keyframes' components; None with fewer
    than :data:`MIN_KEYFRAMES` of them."""
    k = len(components)
    if k < MIN_KEYFRAMES:
        return None
    rhos = np.array([c.rho for c in components])
    mean = float(rhos.mean())
    se = float(rhos.std(ddof=1)) / np.sqrt(k)
    upper = mean + float(special.stdtrit(k - 1, CONFIDENCE)) * se
    return CellCorrelation(rho=mean, standard_error=se, upper=min(upper, 1.0), keyframes=k)


def design_effect(rho: float, mean_cell_size: float) -> float:
    """Kish's ``1 + (m - 1) rho``: how much more an estimate from cells of size-weighted
    mean size ``m`` varies than from as many independent correspondences."""
    return 1.0 + max(mean_cell_size - 1.0, 0.0) * max(rho, 0.0)


def mean_cell_size(cells: IntArray) -> float:
    """``sum m_g^2 / sum m_g`` over the occupied cells of ``cells`` (N,); 0 for none."""
    counts = np.bincount(np.asarray(cells, np.int64))
    total = counts.sum()
    return float((counts.astype(np.float64) ** 2).sum() / total) if total else 0.0
