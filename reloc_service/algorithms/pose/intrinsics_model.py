"""The intrinsics error model of the intrinsics test (:mod:`.intrinsics`): a query's pixels
under a focal and radial distortion error ``theta = (a, b)`` relative to the camera it claims,
``centre + (1 + a) v + b |u|^2 u`` with ``v`` the offset from the principal point and ``u`` it
over the reference radius (the farthest image corner), and their Jacobians with respect to
the pose and ``theta``. Compiled passes (:mod:`.intrinsics_kernels`) give the same values."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from . import intrinsics_kernels

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class IntrinsicsModel:
    """The intrinsics error model of a camera: its principal point and reference radius."""

    centre: Array
    radius_px: float

    def __init__(self, camera: Camera) -> None:
        corners = np.array([[-0.5, -0.5], [camera.width - 0.5, -0.5],
                            [-0.5, camera.height - 0.5], [camera.width - 0.5, camera.height - 0.5]])
        centre = np.array([camera.cx, camera.cy])
        object.__setattr__(self, "centre", centre)
        object.__setattr__(self, "radius_px", float(np.linalg.norm(corners - centre, axis=1).max()))

    def apply(self, projected_px: Array, jac: Array, theta: Array) -> tuple[Array, Array, Array]:
        """Pixels (M, 2) under ``theta`` of points the given camera projects to
        ``projected_px``, their (M, 2, 6) pose Jacobian (from the given camera's ``jac``)
        and (M, 2, 2) Jacobian w.r.t. ``theta``."""
        full = self.jacobian(projected_px, jac, theta)
        return self.pixels(projected_px, theta), full[:, :, :6], full[:, :, 6:]

    def pixels(self, projected_px: Array, theta: Array) -> Array:
        """(M, 2) pixels under ``theta`` of points the given camera projects to
        ``projected_px`` (each row from its own row alone)."""
        a, b = theta
        v = projected_px - self.centre
        u = v / self.radius_px
        r2 = (u * u).sum(axis=1)
        g = u * r2[:, None]  # |g| = 1 at the farthest corner
        return self.centre + (1.0 + a) * v + b * g

    def residuals(self, projected_px: Array, px: Array, theta: Array) -> tuple[Array, Array]:
        """(M, 2) residuals ``px - pixels`` and (M,) their squared lengths (inf where not
        finite): one compiled pass where numba is installed (:mod:`.intrinsics_kernels`,
        the same values)."""
        kernels = intrinsics_kernels.compiled()
        if kernels is None:
            residuals = px - self.pixels(projected_px, theta)
            squared = (residuals**2).sum(axis=1)
            return residuals, np.where(np.isfinite(squared), squared, np.inf)
        residuals, squared = np.empty((len(px), 2)), np.empty(len(px))
        kernels.model_residuals(np.ascontiguousarray(projected_px, np.float64),
                                np.ascontiguousarray(px, np.float64), *self._numbers(theta),
                                residuals, squared)
        return residuals, squared

    def jacobian_of(self, projected_px: Array, jac: Array, rows: npt.NDArray[np.int64],
                    theta: Array) -> Array:
        """:meth:`jacobian` of the correspondences ``rows`` alone (a row's Jacobian is its
        own row's): one compiled pass where numba is installed (the same values)."""
        kernels = intrinsics_kernels.compiled()
        if kernels is None:
            return self.jacobian(projected_px[rows], jac[rows], theta)
        full = np.empty((len(rows), 2, 8))
        kernels.model_jacobian(np.ascontiguousarray(projected_px, np.float64),
                               np.ascontiguousarray(jac, np.float64),
                               np.ascontiguousarray(rows, np.int64), *self._numbers(theta), full)
        return full

    def _numbers(self, theta: Array) -> tuple[float, float, float, float, float]:
        """The kernels' scalars: principal point, reference radius, ``theta``'s a and b."""
        return (float(self.centre[0]), float(self.centre[1]), self.radius_px,
                float(theta[0]), float(theta[1]))

    def jacobian(self, projected_px: Array, jac: Array, theta: Array) -> Array:
        """(M, 2, 8) Jacobian of :meth:`pixels` w.r.t. the pose (6, from the given camera's
        ``jac`` (M, 2, 6)) and ``theta`` (2), each row from its own row alone (so a caller
        differentiates only the rows it keeps)."""
        a, b = theta
        v = projected_px - self.centre
        u = v / self.radius_px
        r2 = (u * u).sum(axis=1)
        # d pixels / d v = (1 + a) I + b (|u|^2 I + 2 u u^T) / R
        dv = (2.0 * b / self.radius_px) * u[:, :, None] * u[:, None, :]
        diagonal = 1.0 + a + b * r2 / self.radius_px
        dv[:, 0, 0] += diagonal
        dv[:, 1, 1] += diagonal
        full = np.empty((len(v), 2, 8))
        # dv @ jac per row with its two-term sums written out (einsum's products, summed in
        # its order, without its per-call cost: the test builds these dozens of times per
        # pose), then d pixels / d theta = [v, g], written in place of a stack.
        np.multiply(dv[:, :, 0, None], jac[:, None, 0, :], out=full[:, :, :6])
        full[:, :, :6] += dv[:, :, 1, None] * jac[:, None, 1, :]
        full[:, :, 6] = v
        np.multiply(u, r2[:, None], out=full[:, :, 7])
        return full
