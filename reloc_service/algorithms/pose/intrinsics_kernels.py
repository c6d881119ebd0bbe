"""The intrinsics test's per-correspondence model compiled (numba, the optional ``[jit]``
extra), with the numpy path's values bit for bit.

:func:`.intrinsics.check_intrinsics` builds its normal equations dozens of times per pose (each
focal start, each Gauss-Newton step, each halving), each time modelling every correspondence
under ``theta`` and differentiating the gated ones: about twenty small numpy operations on a
few hundred rows, whose per-call cost, not their arithmetic, is what the test spends.
:func:`_model_residuals` and :func:`_model_jacobian` do that in one pass each, with every
element computed by the same operations in the same order as :class:`.intrinsics_model.IntrinsicsModel`'s
numpy expressions (no fused multiply-add: numba contracts nothing without ``fastmath``), so
the residuals, gates, Jacobians and hence the normal equations (still summed by numpy) are
the numpy path's exactly (``tests/test_intrinsics_kernels.py`` compares both).
:func:`compiled` imports numba on first use and returns None where it is not installed.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from ...core.numeric import numba_or_none

Array = npt.NDArray[np.float64]


def _model_residuals(projected_px: Array, px: Array, cx: float, cy: float, radius_px: float,
                     a: float, b: float, residuals: Array, squared: Array) -> None:
    """``residuals[m] = px[m] - pixels(projected_px[m])`` under ``theta = (a, b)`` (the
    model of :meth:`.intrinsics_model.IntrinsicsModel.pixels`) and ``squared[m]`` its squared length (inf
    where not finite)."""
    one_a = 1.0 + a
    for m in range(projected_px.shape[0]):
        v0 = projected_px[m, 0] - cx
        v1 = projected_px[m, 1] - cy
        u0 = v0 / radius_px
        u1 = v1 / radius_px
        r2 = u0 * u0 + u1 * u1
        r0 = px[m, 0] - ((cx + one_a * v0) + b * (u0 * r2))
        r1 = px[m, 1] - ((cy + one_a * v1) + b * (u1 * r2))
        residuals[m, 0] = r0
        residuals[m, 1] = r1
        s = r0 * r0 + r1 * r1
        squared[m] = s if math.isfinite(s) else math.inf


def _model_jacobian(projected_px: Array, jac: Array, rows: npt.NDArray[np.int64], cx: float,
                    cy: float, radius_px: float, a: float, b: float, full: Array) -> None:
    """``full[i]`` (2, 8): the pose (from the given camera's ``jac[rows[i]]`` (2, 6)) and
    ``theta`` Jacobian of the model's pixels of correspondence ``rows[i]``
    (:meth:`.intrinsics_model.IntrinsicsModel.jacobian`)."""
    scale = 2.0 * b / radius_px
    one_a = 1.0 + a
    for i in range(rows.shape[0]):
        m = rows[i]
        v0 = projected_px[m, 0] - cx
        v1 = projected_px[m, 1] - cy
        u0 = v0 / radius_px
        u1 = v1 / radius_px
        r2 = u0 * u0 + u1 * u1
        diagonal = one_a + b * r2 / radius_px
        d00 = scale * u0 * u0 + diagonal
        d01 = scale * u0 * u1
        d10 = scale * u1 * u0
        d11 = scale * u1 * u1 + diagonal
        for k in range(6):
            full[i, 0, k] = d00 * jac[m, 0, k] + d01 * jac[m, 1, k]
            full[i, 1, k] = d10 * jac[m, 0, k] + d11 * jac[m, 1, k]
        full[i, 0, 6] = v0
        full[i, 1, 6] = v1
        full[i, 0, 7] = u0 * r2
        full[i, 1, 7] = u1 * r2


class IntrinsicsKernels(NamedTuple):
    """The compiled functions (see the module's doc)."""

    model_residuals: Any
    model_jacobian: Any


@functools.cache
def compiled() -> IntrinsicsKernels | None:
    """The kernels compiled by numba (cached on disk by numba after the first compile), or
    None where numba is not installed."""
    numba = numba_or_none()
    if numba is None:
        return None
    jit: Any = numba.njit(cache=True, nogil=True)
    return IntrinsicsKernels(jit(_model_residuals), jit(_model_jacobian))


def warm_up() -> None:
    """Load (or compile) every kernel now, on a few correspondences."""
    k = compiled()
    if k is None:
        return
    px = np.array([[10.0, 20.0], [300.0, 200.0]])
    k.model_residuals(px, px, 320.0, 240.0, 400.0, 0.01, 0.02, np.empty((2, 2)), np.empty(2))
    k.model_jacobian(px, np.ones((2, 2, 6)), np.array([1], np.int64), 320.0, 240.0, 400.0,
                     0.01, 0.02, np.empty((1, 2, 8)))
