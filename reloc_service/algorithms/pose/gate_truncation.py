"""The keypoint noise a pose's inliers show once the inlier gate's truncation is undone.

A pose keeps the correspondences whose reprojection error is below a fixed radius ``c``
(``max_reproj_error_px``) and states ``sigma^2 (J^T W J)^-1`` with ``sigma^2`` the weighted
mean square of those inliers' residuals. Where the keypoint noise is small against ``c`` the
gate removes nothing of it; where it is not (a blurred query: its keypoints move by about a
fifth of the blur's extent, 2-3.5 px per axis at 8-14 px of blur,
``scripts/blur_shift.py``), the gate cuts the noise's tails, the kept residuals are smaller
than the noise the pose's error is made of, and the stated covariance is too thin
(``scripts/gate_truncation_mc.py``, a 5 px gate: 3.2 % of the position errors beyond 3 sigma
at 1 px of noise per axis, 28.5 % at 3 px; 3.2 % and 4.9 % with this module's variance).

For an inlier of weight ``w`` (inverse variance in units of a level-0 keypoint's) the noise
is isotropic Gaussian with ``sigma^2 / w`` per axis; kept within radius ``c`` its squared
length averages ``2 (sigma^2 / w) g(a)``, ``a = c^2 w / (2 sigma^2)``,
``g(a) = 1 - a e^-a / (1 - e^-a)`` (the Rayleigh distribution truncated at ``c``). The
weighted sum of squares then averages ``sigma^2 (2 sum_i g(a_i) - 6)`` (6: the pose's degrees
of freedom, as the plain estimate counts them): :func:`untruncated_variance` solves this for
``sigma^2`` by bisection (the left side grows with ``sigma^2``). Where the residuals are as
wide as the gate allows (the solution beyond the point where the median inlier's gate is its
1-sigma radius, ``a = 1/2``: 39 % of its noise kept), that bound is stated.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

#: The bisection's steps over a factor of ``_SPAN`` in ``sigma^2``: 2^-60 of it.
_STEPS = 60
_SPAN = 1e4


def kept_share(a: Array) -> Array:
    """``g(a)``: the mean squared length of a 2-D isotropic Gaussian kept within the radius
    where ``a = c^2 / (2 sigma_axis^2)``, over its untruncated mean ``2 sigma_axis^2``."""
    a = np.maximum(np.asarray(a, np.float64), 1e-12)
    return np.asarray(1.0 - a * np.exp(-a) / -np.expm1(-a), np.float64)


def untruncated_variance(weights: npt.ArrayLike, weighted_sq: float, gate_px: float) -> float:
    """The level-0 keypoint variance per axis (px^2) whose Gaussian noise, truncated by the
    gate of radius ``gate_px`` at each inlier's ``weights``, leaves the observed
    ``weighted_sq`` (sum of ``w r^2`` over the inliers), with the plain estimate's 6 degrees
    of freedom; at least the plain ``weighted_sq / (2 n - 6)``, at most the bound of the
    module docstring. NaN with fewer than 4 inliers or a non-positive gate."""
    w = np.asarray(weights, np.float64)
    n = len(w)
    if n < 4 or gate_px <= 0 or not np.all(w > 0) or weighted_sq <= 0:
        return float("nan")
    plain = weighted_sq / max(2 * n - 6, 1)
    cap = gate_px**2 * float(np.median(w))         # a = 1/2 for the median inlier
    if cap <= plain:
        return plain

    def expected(s2: float) -> float:
        return s2 * (2.0 * float(kept_share(gate_px**2 * w / (2.0 * s2)).sum()) - 6.0)

    if expected(cap) <= weighted_sq:
        return cap
    low, high = np.log(plain), np.log(min(cap, plain * _SPAN))
    if expected(float(np.exp(high))) <= weighted_sq:
        return float(np.exp(high))
    for _ in range(_STEPS):
        mid = 0.5 * (low + high)
        if expected(float(np.exp(mid))) < weighted_sq:
            low = mid
        else:
            high = mid
    return float(np.exp(0.5 * (low + high)))


def truncation_factor(weights: npt.ArrayLike, weighted_sq: float, gate_px: float) -> float:
    """How many times the plain ``sigma^2`` (``weighted_sq / (2 n - 6)``) the untruncated
    one is (:func:`untruncated_variance`): 1 where the gate cut nothing, NaN where unknown."""
    n = len(np.asarray(weights))
    s2 = untruncated_variance(weights, weighted_sq, gate_px)
    return s2 / (weighted_sq / max(2 * n - 6, 1)) if np.isfinite(s2) else float("nan")
