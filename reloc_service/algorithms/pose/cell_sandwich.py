"""The measurement covariance a pose states, widened where its own inliers show more spread
than the model covariance says: the cluster-robust (sandwich) covariance over the cells of
the verification's coverage grid (Liang & Zeger 1986; Cameron & Miller 2015, eq. 11), whose
excess over the model ``d C`` is taken only along the directions where it is larger than
honest residuals make it at a stated false-alarm rate.

The model covariance ``C = sigma^2 (J^T W J)^-1`` assumes independent residuals. On degraded
images (blur, noise) a query's keypoints are displaced coherently within a region and some of
its in-gate correspondences are wrong, so its residuals are correlated within each region and
the pose is off by more than ``C`` says, while their overall scale (``sigma^2``, already the
residuals' own) stays near the stated keypoint noise: a variance factor from the residuals'
scale cannot see it. The sandwich ``N^-1 (sum_g s_g s_g^T) N^-1 G / (G - 1)`` (``s_g`` the
weighted score ``J_g^T W_g r_g`` of cell g, ``N = J^T W J``) measures the spread the cells
actually show. It is noisy (``G`` cells: whitened by ``C`` where the model holds, about a Wishart
matrix with ``G - 1`` degrees of freedom over ``G - 1``), so it widens ``C`` only along the
whitened directions where it exceeds the ``1 - false_alarm`` quantile of that matrix's
largest eigenvalue, to its own value there: an honest query is widened at about the
``false_alarm`` rate, and never narrowed.
"""

from __future__ import annotations

import functools

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

#: The share of queries whose residuals agree with their model covariance that are widened.
FALSE_ALARM = 0.01

#: Draws of the Monte Carlo quantile of :func:`spread_limit` (its 1 % tail holds 200 of them).
LIMIT_DRAWS = 20000

#: Fewest occupied cells with which the cells' spread says anything (two leave one degree of
#: freedom after the fit's own constraint).
MIN_CELLS = 3


def grid_cells(px: Array, image_size: tuple[int, int], grid: int) -> npt.NDArray[np.int64]:
    """(N,) the cell of a ``grid`` x ``grid`` partition of the image of (N, 2) pixels ``px``."""
    width, height = image_size
    col = np.clip(((px[:, 0] + 0.5) * grid // width).astype(np.int64), 0, grid - 1)
    row = np.clip(((px[:, 1] + 0.5) * grid // height).astype(np.int64), 0, grid - 1)
    return np.asarray(row * grid + col, np.int64)


def cell_sandwich(normal_inverse: Array, scores: Array, cells: npt.NDArray[np.int64]
                  ) -> tuple[Array, int] | None:
    """(6, 6) the sandwich covariance ``N^-1 M N^-1`` of a pose from its (N, 6) per-point
    weighted scores ``J_i^T W_i r_i`` grouped by (N,) ``cells`` (``M`` the sum over cells of
    each cell's summed score's outer product, times ``G / (G - 1)``) and the number ``G`` of
    occupied cells; None with fewer than :data:`MIN_CELLS` or a singular ``normal_inverse``."""
    occupied, group = np.unique(cells, return_inverse=True)
    g = len(occupied)
    if g < MIN_CELLS or not np.all(np.isfinite(normal_inverse)) or not np.all(np.isfinite(scores)):
        return None
    summed = np.zeros((g, scores.shape[1]))
    np.add.at(summed, group, scores)
    meat = summed.T @ summed * (g / (g - 1.0))
    out = normal_inverse @ meat @ normal_inverse
    return np.asarray(0.5 * (out + out.T), np.float64), g


def point_sandwich(normal_inverse: Array, scores: Array, informations: Array
                   ) -> tuple[Array, int] | None:
    """:func:`cell_sandwich` with each of the (N, 6) ``scores`` its own cell (White's
    heteroskedasticity-robust covariance) and, in place of the number of cells, the
    effective number (:func:`effective_cells`) of the points' (N, 6, 6) ``informations``
    ``J_i^T W_i J_i``; None where fewer than :data:`MIN_CELLS`."""
    cells = effective_cells(normal_inverse, informations)
    out = cell_sandwich(normal_inverse, scores, np.arange(len(scores), dtype=np.int64))
    return None if out is None or cells < MIN_CELLS else (out[0], cells)


def effective_cells(normal_inverse: Array, informations: Array) -> int:
    """How many equal cells the points of (N, 6, 6) ``informations`` ``A_i`` weigh as: whitened
    by the model, point i's score has covariance ``B_i = N^-1/2 A_i N^-1/2`` (the ``B_i`` sum
    to the identity), and the whitened sandwich's trace has variance ``2 sum_i tr(B_i^2)``,
    which a ``W_6(nu, I) / nu`` matches with ``nu = 6 / sum_i tr(B_i^2)`` (Satterthwaite
    1946): ``nu = G`` for ``G`` equal cells, fewer where a few points carry a direction
    (the farthest from the image's centre, the rotation about the optical axis). ``nu``
    rounded down (a higher limit where in doubt), counted as cells as :func:`cell_sandwich`
    counts them (one degree of freedom to the fit)."""
    moved = np.asarray(informations, np.float64) @ np.asarray(normal_inverse, np.float64)
    spread = float(np.einsum("nij,nji->", moved, moved))
    if not np.isfinite(spread) or spread <= 0:
        return 0
    return int(np.floor(6.0 / spread + 1e-9))


def spread_limit(cells: int, false_alarm: float = FALSE_ALARM) -> float:
    """The largest whitened eigenvalue of the sandwich that honest residuals exceed with
    probability ``false_alarm``, for ``G`` ``cells`` (:func:`simulated_limit`; at the default
    rate, the values it gives for the cells of a 4 x 4 grid, :data:`SPREAD_LIMITS`)."""
    if false_alarm == FALSE_ALARM and cells in SPREAD_LIMITS:
        return SPREAD_LIMITS[cells]
    if false_alarm == FALSE_ALARM and cells > max(SPREAD_LIMITS):
        return tracy_widom_limit(cells)
    return simulated_limit(cells, false_alarm)


#: The 99 % quantile of the Tracy-Widom law of order 1 (Tracy & Widom 1996; the largest
#: eigenvalue of a real Wishart matrix, centred and scaled, tends to it).
TRACY_WIDOM_1_Q99 = 2.0234


def tracy_widom_limit(cells: int, dim: int = 6) -> float:
    """:func:`simulated_limit` at :data:`FALSE_ALARM` in closed form for many ``cells`` (each
    inlier its own, say): the largest eigenvalue of ``W_dim(n, I)``, ``n = G - 1``, is about
    ``mu + sigma TW_1`` with ``mu = (sqrt(n - 1/2) + sqrt(dim - 1/2))^2`` and ``sigma =
    sqrt(mu) (1 / sqrt(n - 1/2) + 1 / sqrt(dim - 1/2))^(1/3)`` (Johnstone 2001, Theorem 1.1);
    divided by ``n``. Within 1 % of the simulated quantile from 8 cells to 250 (the test
    checks), without the simulation's seconds for hundreds of cells."""
    n = max(cells - 1, 1)
    a, b = np.sqrt(n - 0.5), np.sqrt(dim - 0.5)
    mu = (a + b) ** 2
    sigma = (a + b) * (1.0 / a + 1.0 / b) ** (1.0 / 3.0)
    return float((mu + sigma * TRACY_WIDOM_1_Q99) / n)


@functools.lru_cache(maxsize=64)
def simulated_limit(cells: int, false_alarm: float) -> float:
    """The ``1 - false_alarm`` quantile of the largest eigenvalue of ``W_6(G - 1, I) / (G -
    1)`` for ``G`` ``cells`` (the cells' scores whitened by the model, equal in size, their
    sum zero at the fit), from :data:`LIMIT_DRAWS` draws seeded 0 (cached per ``G``)."""
    dof = max(cells - 1, 1)
    draws = np.random.default_rng(0).standard_normal((LIMIT_DRAWS, dof, 6))
    largest = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", draws, draws))[:, -1] / dof
    return float(np.quantile(largest, 1.0 - false_alarm))


#: :func:`simulated_limit` at :data:`FALSE_ALARM` for 3 to 16 cells (the coverage grid's
#: 4 x 4), as it computes them (tests/test_cell_sandwich.py checks): computed cold, each
#: takes a tenth of a second or more, which an answer should not wait for.
SPREAD_LIMITS: dict[int, float] = {
    3: 10.422398252013323,
    4: 7.8725033606349335,
    5: 6.640518923059197,
    6: 5.822225473771925,
    7: 5.248163944774253,
    8: 4.786212932243556,
    9: 4.484992406554347,
    10: 4.219886511661586,
    11: 3.9572054303519817,
    12: 3.796476704202329,
    13: 3.6785304620334918,
    14: 3.476898101183332,
    15: 3.3650028021932568,
    16: 3.2650496952803683,
}


def widened(covariance: Array, sandwich: Array, cells: int,
            false_alarm: float = FALSE_ALARM) -> Array:
    """(6, 6) ``covariance`` with its whitened eigenvalues replaced by the ``sandwich``'s
    (whitened by ``covariance``) where those exceed :func:`spread_limit` (module docstring);
    ``covariance`` itself where either is not finite or it is not positive definite."""
    if not (np.all(np.isfinite(covariance)) and np.all(np.isfinite(sandwich))):
        return covariance
    values, vectors = np.linalg.eigh(covariance)
    if not np.all(values > 0):
        return covariance
    root = vectors * np.sqrt(values)                                  # covariance = root root^T
    inv_root = np.linalg.inv(root)
    whitened = inv_root @ sandwich @ inv_root.T
    w_values, w_vectors = np.linalg.eigh(0.5 * (whitened + whitened.T))
    limit = spread_limit(cells, false_alarm)
    lifted = (w_vectors * np.where(w_values > limit, w_values, 1.0)) @ w_vectors.T
    out = root @ lifted @ root.T
    return np.asarray(0.5 * (out + out.T), np.float64)
