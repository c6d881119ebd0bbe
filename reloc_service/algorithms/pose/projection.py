"""Projection through a camera model for the pose solvers: pixels of camera-frame points, their
Jacobian w.r.t. the pose (a right perturbation of ``world_from_cam``) and w.r.t. normalised
coordinates, undistortion, and PoseLib's camera with the same model. Compiled for pinhole and
radtan cameras where numba is installed (:mod:`.kernels`, the same values); numpy otherwise."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import poselib

from ...core.cameras import CV_UNDISTORT_CRITERIA, UNDISTORT_NEWTON_ITERS, Camera, RadTanCamera
from ...core.geometry import invert, transform_points
from .kernels import camera_params, compiled

Array = npt.NDArray[np.float64]

#: PoseLib's camera model with the same projection as each of ours (parameters fx fy cx cy,
#: then our distortion values in the same order; tests/test_pose_p3p.py projects through both).
#: A 5-value radtan (k3) is PoseLib's FULL_OPENCV with k4 = k5 = k6 = 0.
_POSELIB_MODELS = {"pinhole": "PINHOLE", "radtan": "OPENCV", "equidistant": "OPENCV_FISHEYE"}

#: Step of the central differences of the fov distortion's Jacobian (normalised coordinates):
#: PoseLib 2.0.5 has no FOV model (``poselib.Camera("FOV", ...)`` is its NULL model).
_DISTORT_STEP = 1e-6


@functools.lru_cache(maxsize=64)
def kernel_camera(camera: Camera) -> tuple[Array, bool] | None:
    """:func:`.kernels.camera_params` of ``camera`` (made once per camera)."""
    return camera_params(camera)


def project_cam(camera: Camera, points_cam: Array) -> Array:
    """``camera.project`` of (N, 3) camera-frame points: compiled for pinhole and radtan
    cameras where numba is installed (:mod:`.kernels`, the same values)."""
    kernels, params = compiled(), kernel_camera(camera)
    if kernels is None or params is None:
        return camera.project(points_cam)
    out = np.empty((len(points_cam), 2))
    kernels.project(np.ascontiguousarray(points_cam, np.float64), params[0], params[1], out)
    return out


def undistort_pixels(camera: Camera, px: Array) -> Array:
    """``camera.undistort_pixels`` of (N, 2) pixels: for radtan compiled where numba is
    installed (:mod:`.kernels`: OpenCV's start and the Newton iterations, the same values)."""
    kernels, params = compiled(), kernel_camera(camera)
    if kernels is None or params is None or not params[1] or not isinstance(camera, RadTanCamera):
        return camera.undistort_pixels(px)
    out = np.empty((len(px), 2))
    kernels.undistort_pixels(np.ascontiguousarray(px, np.float64), params[0],
                             CV_UNDISTORT_CRITERIA[1], UNDISTORT_NEWTON_ITERS, out)
    return out


def pose_jacobian(camera: Camera, points_cam: Array) -> Array:
    """(2N, 6) Jacobian of the pixels of (N, 3) camera-frame points w.r.t. a right
    perturbation of ``world_from_cam`` (as :mod:`.pnp`'s Gauss-Newton takes it); compiled
    like :func:`project_cam`."""
    kernels, params = compiled(), kernel_camera(camera)
    if kernels is not None and params is not None:
        out = np.empty((2 * len(points_cam), 6))
        kernels.pose_jacobian(np.ascontiguousarray(points_cam, np.float64), params[0],
                              params[1], out)
        return out
    d_px = _projection_jacobian(camera, points_cam)  # (N, 2, 3)
    # cam_from_world becomes exp(-xi) @ cam_from_world, so p_cam moves by -rho + [p_cam]x omega:
    # d px / d rho = -d_px, d px / d omega = d_px @ [p_cam]x (columns written out).
    x, y, z = (points_cam[:, None, i] for i in range(3))
    a0, a1, a2 = d_px[:, :, 0], d_px[:, :, 1], d_px[:, :, 2]
    jac = np.stack([-a0, -a1, -a2, a1 * z - a2 * y, a2 * x - a0 * z, a0 * y - a1 * x], axis=2)
    return jac.reshape(-1, 6)


def _projection_jacobian(camera: Camera, points_cam: Array) -> Array:
    """(N, 2, 3) derivative of pixels w.r.t. camera-frame points: K * distortion * pinhole."""
    inv_z = 1.0 / points_cam[:, 2]
    xy = points_cam[:, :2] * inv_z[:, None]
    d_xy = pixel_jacobian(camera, xy)  # (N, 2, 2) d px / d xy
    # d xy / d p = [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]
    d_dz = -np.einsum("nij,nj->ni", d_xy, xy)
    return np.concatenate([d_xy, d_dz[:, :, None]], axis=2) * inv_z[:, None, None]


def pixel_jacobian(camera: Camera, xy: Array) -> Array:
    """(N, 2, 2) derivative of pixels w.r.t. normalised coordinates ``xy`` (N, 2): PoseLib's
    analytic Jacobian of the same camera model (written out in numpy for pinhole and radtan:
    PoseLib returns a list of 2x2 arrays whose conversion costs more than the maths), or
    central differences for fov."""
    if isinstance(camera, RadTanCamera):
        dxx, dxy, dyx, dyy = camera._jacobian(xy[:, 0], xy[:, 1])
        jac = np.empty((len(xy), 2, 2))
        jac[:, 0, 0], jac[:, 0, 1] = camera.fx * dxx, camera.fx * dxy
        jac[:, 1, 0], jac[:, 1, 1] = camera.fy * dyx, camera.fy * dyy
        return jac
    if camera.model == "pinhole":
        return np.broadcast_to(np.diag([camera.fx, camera.fy]), (len(xy), 2, 2)).copy()
    model = poselib_camera(camera)
    if model is not None:
        return np.asarray(model.project_with_jac(np.ascontiguousarray(xy))[1]).reshape(-1, 2, 2)
    h = _DISTORT_STEP
    d_dx = (camera.distort(xy + [h, 0.0]) - camera.distort(xy - [h, 0.0])) / (2 * h)  # (N, 2)
    d_dy = (camera.distort(xy + [0.0, h]) - camera.distort(xy - [0.0, h])) / (2 * h)
    return np.stack([d_dx, d_dy], axis=2) * np.array([camera.fx, camera.fy])[None, :, None]


@functools.lru_cache(maxsize=64)
def poselib_camera(camera: Camera) -> poselib.Camera | None:
    """PoseLib's camera with the same projection as ``camera``; None for fov (not in
    PoseLib 2.0.5)."""
    params = [camera.fx, camera.fy, camera.cx, camera.cy, *camera.distortion]
    name = _POSELIB_MODELS.get(camera.model)
    if camera.model == "radtan" and len(camera.distortion) == 5:
        name, params = "FULL_OPENCV", [*params, 0.0, 0.0, 0.0]
    return None if name is None else poselib.Camera(name, params, camera.width, camera.height)


def pose_projector(points_world: Array, camera: Camera) -> PoseProjector:
    """The projection of (N, 3) ``points_world`` through ``camera`` at a ``world_from_cam``
    (what :func:`.intrinsics.check_intrinsics` differentiates): called, (N, 2) pixels and
    their (N, 2, 6) Jacobian w.r.t. a right perturbation of the pose."""
    return PoseProjector(points_world, camera)


@dataclass(frozen=True, eq=False)
class PoseProjector:
    """(N, 3) ``points_world`` projected through ``camera`` at a pose: the pixels of all of
    them (:meth:`pixels`) and the Jacobian of some (:meth:`jacobian`), apart, because the
    intrinsics test's Gauss-Newton tries steps on every point and differentiates only the
    gated points of the steps it takes (each row's values are its own row's either way)."""

    points_world: Array
    camera: Camera

    def __call__(self, world_from_cam: Array) -> tuple[Array, Array]:
        px, points_cam = self.pixels(world_from_cam)
        return px, self.jacobian(points_cam)

    def pixels(self, world_from_cam: Array) -> tuple[Array, Array]:
        """(N, 2) pixels and (N, 3) camera-frame points at ``world_from_cam``."""
        points_cam = transform_points(invert(world_from_cam), self.points_world)
        return project_cam(self.camera, points_cam), points_cam

    def pixels_many(self, world_from_cams: Array) -> tuple[Array, Array]:
        """(K, N, 2) pixels and (K, N, 3) camera-frame points at each of K poses (K, 4, 4)
        at once (as :meth:`pixels`, equal to rounding)."""
        rotation, position = world_from_cams[:, :3, :3], world_from_cams[:, None, :3, 3]
        points_cam = (self.points_world[None] - position) @ rotation  # R^T (p - t) per row
        px = project_cam(self.camera, points_cam.reshape(-1, 3))
        return px.reshape(*points_cam.shape[:2], 2), points_cam

    def jacobian(self, points_cam: Array) -> Array:
        """(M, 2, 6) pixel Jacobian of (M, 3) camera-frame points w.r.t. a right perturbation
        of ``world_from_cam``."""
        return pose_jacobian(self.camera, points_cam).reshape(-1, 2, 6)
