"""How well world points are known along the rays of the keyframes that made them, and that
uncertainty as the query's pixels at a pose: the weight a residual gets in the PnP refinement
(:mod:`.pnp`) and the width of a guided search window (:mod:`.prior_windows`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.geometry import invert, transform_points
from .kernels import compiled
from .projection import project_cam

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class PointUncertainty:
    """How well N world points are known: 1-sigma ``depth_sigmas_m`` (N,) along the rays from
    ``ray_origins_world`` (N, 3) (the centre of a keyframe that observes each)."""

    depth_sigmas_m: Array
    ray_origins_world: Array

    def take(self, rows: npt.NDArray[np.int64]) -> PointUncertainty:
        """The uncertainty of points ``rows`` alone."""
        return PointUncertainty(self.depth_sigmas_m[rows], self.ray_origins_world[rows])

    def pixel_sigmas(self, world_from_cam: Array, points_world: Array, camera: Camera,
                     rows: npt.NDArray[np.int64] | slice = slice(None), *,
                     projected_px: Array | None = None) -> Array:
        """(M,) the depth uncertainty of points ``rows`` as seen from ``world_from_cam``:
        pixels between a point and the point moved one sigma along its ray.
        ``projected_px`` (M, 2): the points' pixels at that pose when already known."""
        pts = points_world
        kernels = compiled()
        if kernels is None:
            ray = pts - self.ray_origins_world[rows]
            ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
            moved = pts + self.depth_sigmas_m[rows, None] * ray
        else:
            moved = np.empty_like(pts, np.float64)
            kernels.moved_points(np.ascontiguousarray(pts, np.float64),
                                 np.ascontiguousarray(self.ray_origins_world[rows], np.float64),
                                 np.ascontiguousarray(self.depth_sigmas_m[rows], np.float64),
                                 moved)
        cam_from_world = invert(world_from_cam)
        with np.errstate(invalid="ignore", divide="ignore"):
            # Per-point arithmetic: projecting a point alone or among others gives its values.
            if projected_px is None:
                both = project_cam(camera, transform_points(cam_from_world,
                                                            np.concatenate([moved, pts])))
                moved_px, projected_px = both[:len(pts)], both[len(pts):]
            else:
                moved_px = project_cam(camera, transform_points(cam_from_world, moved))
            if kernels is not None:
                sigma = np.empty(len(pts))
                kernels.pixel_distances(moved_px, np.ascontiguousarray(projected_px), sigma)
                return sigma
            sigma = np.linalg.norm(moved_px - projected_px, axis=1)
        return np.where(np.isfinite(sigma), sigma, np.inf)
