"""Camera models, vectorised: pinhole, radtan (OpenCV k1 k2 p1 p2 [k3]), equidistant (OpenCV
fisheye k1..k4) and fov (the ATAN model of PTAM and SVO, Devernay and Faugeras 2001).

Every model maps camera-frame points to pixels through normalised image coordinates
``xy = (X/Z, Y/Z)``: ``px = K @ distort(xy)``. Pixel centres are at integer coordinates
(OpenCV convention). Unprojection inverts the distortion by Newton iterations, so a
project/unproject round trip is exact to well below 1e-6 px over the whole image.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, ClassVar

import cv2
import numpy as np
import numpy.typing as npt
from reloc_client.protocol.geometry import CAMERA_MODELS as DISTORTION_COUNTS

from .errors import CameraError

Array = npt.NDArray[np.float64]

CAMERA_MODELS: dict[str, type[Camera]] = {}

UNDISTORT_NEWTON_ITERS = 30
#: OpenCV's fixed-point radtan undistortion as Newton's start: 40 iterations leave about
#: 1e-15 in normalised coordinates on a strong (k1 = -0.28) lens, one Newton step checks it.
CV_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT, 40, 0.0)


def register_camera(name: str):
    """Class decorator: register a camera model under ``name`` (its dict's ``model``); its
    accepted numbers of distortion values come from the wire protocol's table, the one
    definition the client validates against too."""

    def deco(cls: type[Camera]) -> type[Camera]:
        if name in CAMERA_MODELS:
            raise ValueError(f"duplicate camera model {name!r}")
        if name not in DISTORTION_COUNTS:
            raise ValueError(f"camera model {name!r} is not in the protocol's table "
                             f"{sorted(DISTORTION_COUNTS)}: add it there first")
        cls.model = name
        cls.n_distortion = DISTORTION_COUNTS[name]
        CAMERA_MODELS[name] = cls
        return cls

    return deco


@dataclass(frozen=True)
class Camera(abc.ABC):
    """Intrinsics of one camera: image size (px), focal lengths and principal point (px),
    and the model's distortion parameters (see each model for their number and meaning)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = field(default=())

    model: ClassVar[str] = ""
    n_distortion: ClassVar[tuple[int, ...]] = (0,)

    def __post_init__(self) -> None:
        vals = [self.fx, self.fy, self.cx, self.cy, *self.distortion]
        if not all(np.isfinite(v) for v in vals):
            raise CameraError(f"{self.model} camera: parameters must be finite, got {vals}")
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"{self.model} camera: expected positive width, height, fx, fy; got "
                              f"{self.width}x{self.height}, fx={self.fx}, fy={self.fy}")
        if len(self.distortion) not in self.n_distortion:
            raise CameraError(f"{self.model} camera: expected {' or '.join(map(str, self.n_distortion))} "
                              f"distortion values, got {len(self.distortion)}")

    # -- model-specific part: normalised coordinates ----------------------------------------
    @abc.abstractmethod
    def distort(self, xy: Array) -> Array:
        """Undistorted normalised coordinates (N, 2) to distorted normalised coordinates (N, 2)."""

    @abc.abstractmethod
    def undistort(self, xy_distorted: Array) -> Array:
        """Inverse of :meth:`distort`, (N, 2) -> (N, 2)."""

    # -- shared part -------------------------------------------------------------------------
    @property
    def K(self) -> Array:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    def project(self, points_cam: npt.ArrayLike) -> Array:
        """(N, 3) points in the camera frame to (N, 2) pixels; NaN for points with Z <= 0."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.where(z > 1e-12, p[:, :2] / np.where(z > 1e-12, z, 1.0), np.nan)
        return self.normalized_to_pixels(self.distort(xy))

    def unproject(self, px: npt.ArrayLike) -> Array:
        """(N, 2) pixels to (N, 3) unit bearing vectors in the camera frame."""
        xy = self.undistort(self.pixels_to_normalized(px))
        b = np.column_stack([xy, np.ones(len(xy))])
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    def undistort_pixels(self, px: npt.ArrayLike) -> Array:
        """(N, 2) distorted pixels to pixels of the ideal pinhole camera with the same K."""
        return self.normalized_to_pixels(self.undistort(self.pixels_to_normalized(px)))

    def pixels_to_normalized(self, px: npt.ArrayLike) -> Array:
        """(N, 2) pixels to distorted normalised coordinates."""
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        # Per column the same two operations as written out per axis (one array each).
        return (p - np.array([self.cx, self.cy])) / np.array([self.fx, self.fy])

    def normalized_to_pixels(self, xy: npt.ArrayLike) -> Array:
        """(N, 2) distorted normalised coordinates to pixels."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return q * np.array([self.fx, self.fy]) + np.array([self.cx, self.cy])

    def in_image(self, px: npt.ArrayLike, *, margin: float = 0.0) -> npt.NDArray[np.bool_]:
        """(N,) mask of pixels inside the image, at least ``margin`` px from the border."""
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return ((p[:, 0] >= -0.5 + margin) & (p[:, 0] <= self.width - 0.5 - margin)
                    & (p[:, 1] >= -0.5 + margin) & (p[:, 1] <= self.height - 0.5 - margin))

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (e.g. 0.5 for a pyramid level)."""
        return type(self)(
            width=max(1, int(round(self.width * factor))),
            height=max(1, int(round(self.height * factor))),
            fx=self.fx * factor, fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5, cy=(self.cy + 0.5) * factor - 0.5,
            distortion=self.distortion,
        )

    def to_dict(self) -> dict[str, Any]:
        """The dataset's camera dict (``cameras.json`` entry, wire format)."""
        return {"model": self.model, "width": int(self.width), "height": int(self.height),
                "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx),
                "cy": float(self.cy), "distortion": [float(d) for d in self.distortion]}


def camera_from_dict(d: dict[str, Any]) -> Camera:
    """Build a camera from the dataset's camera dict; raise CameraError naming what is wrong."""
    if not isinstance(d, dict):
        raise CameraError(f"camera: expected a dict, got {type(d).__name__}")
    model = d.get("model")
    if model not in CAMERA_MODELS:
        raise CameraError(f"camera: unknown model {model!r}; expected one of {sorted(CAMERA_MODELS)}")
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in d]
    if missing:
        raise CameraError(f"{model} camera: missing field(s) {missing}")
    unknown = set(d) - {"model", "width", "height", "fx", "fy", "cx", "cy", "distortion"}
    if unknown:
        raise CameraError(f"{model} camera: unknown field(s) {sorted(unknown)}")
    try:
        dist = tuple(float(v) for v in d.get("distortion", []) or [])
        w, h = d["width"], d["height"]
        if isinstance(w, bool) or isinstance(h, bool) or int(w) != w or int(h) != h:
            raise CameraError(f"{model} camera: width and height must be integers")
        return CAMERA_MODELS[model](
            width=int(w), height=int(h), fx=float(d["fx"]), fy=float(d["fy"]),
            cx=float(d["cx"]), cy=float(d["cy"]), distortion=dist)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, CameraError):
            raise
        raise CameraError(f"{model} camera: parameters must be numbers ({exc})") from exc


@register_camera("pinhole")
@dataclass(frozen=True)
class PinholeCamera(Camera):
    """Ideal pinhole camera; ``distortion`` is empty."""

    def distort(self, xy: Array) -> Array:
        return np.asarray(xy, dtype=np.float64).reshape(-1, 2).copy()

    def undistort(self, xy_distorted: Array) -> Array:
        return np.asarray(xy_distorted, dtype=np.float64).reshape(-1, 2).copy()


@register_camera("radtan")
@dataclass(frozen=True)
class RadTanCamera(Camera):
    """OpenCV radial-tangential (Brown-Conrady) model, ``distortion = [k1, k2, p1, p2(, k3)]``."""

    def _coeffs(self) -> tuple[float, float, float, float, float]:
        k1, k2, p1, p2, *rest = self.distortion
        return k1, k2, p1, p2, (rest[0] if rest else 0.0)

    def distort(self, xy: Array) -> Array:
        k1, k2, p1, p2, k3 = self._coeffs()
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        x, y = q[:, 0], q[:, 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        return np.column_stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y])

    def _jacobian(self, x: Array, y: Array) -> tuple[Array, Array, Array, Array]:
        k1, k2, p1, p2, k3 = self._coeffs()
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        dxx = radial + 2 * x * x * d_radial_dr2 + 2 * p1 * y + 6 * p2 * x
        dxy = 2 * x * y * d_radial_dr2 + 2 * p1 * x + 2 * p2 * y
        dyx = 2 * x * y * d_radial_dr2 + 2 * p1 * x + 2 * p2 * y
        dyy = radial + 2 * y * y * d_radial_dr2 + 6 * p1 * y + 2 * p2 * x
        return dxx, dxy, dyx, dyy

    def undistort(self, xy_distorted: Array) -> Array:
        target = np.asarray(xy_distorted, dtype=np.float64).reshape(-1, 2)
        q = self._initial_undistort(target)
        for _ in range(UNDISTORT_NEWTON_ITERS):  # 2x2 Newton per point, all points at once
            res = self.distort(q) - target
            a, b, c, d = self._jacobian(q[:, 0], q[:, 1])
            det = a * d - b * c
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            step = np.column_stack([(d * res[:, 0] - b * res[:, 1]) / det,
                                    (-c * res[:, 0] + a * res[:, 1]) / det])
            q = q - step
            if np.nanmax(np.abs(step), initial=0.0) < 1e-15:
                break
        return q

    def _initial_undistort(self, target: Array) -> Array:
        """Newton's starting point: OpenCV's fixed-point undistortion (C, a few microseconds),
        close enough that one or two Newton steps (the per-step cost is numpy's) reach the
        same root as from ``target`` itself; ``target`` where OpenCV gives no finite value."""
        if len(target) == 0:
            return target.copy()
        guess = cv2.undistortPoints(np.ascontiguousarray(target).reshape(-1, 1, 2), np.eye(3),
                                    np.asarray(self.distortion, np.float64),
                                    criteria=CV_UNDISTORT_CRITERIA).reshape(-1, 2)
        return np.where(np.isfinite(guess), guess, target)


class _RadialCamera(Camera):
    """A model whose distortion only rescales the radius: r_d = g(r)."""

    @abc.abstractmethod
    def _radius_distort(self, r: Array) -> Array: ...

    @abc.abstractmethod
    def _radius_undistort(self, r_d: Array) -> Array: ...

    def distort(self, xy: Array) -> Array:
        return _rescale_radius(np.asarray(xy, dtype=np.float64).reshape(-1, 2), self._radius_distort)

    def undistort(self, xy_distorted: Array) -> Array:
        return _rescale_radius(np.asarray(xy_distorted, dtype=np.float64).reshape(-1, 2),
                               self._radius_undistort)


def _rescale_radius(q: Array, g) -> Array:
    r = np.linalg.norm(q, axis=1)
    small = r < 1e-12
    r_safe = np.where(small, 1.0, r)
    scale = np.where(small, 1.0, g(r_safe) / r_safe)
    return q * scale[:, None]


@register_camera("equidistant")
@dataclass(frozen=True)
class EquidistantCamera(_RadialCamera):
    """OpenCV fisheye (Kannala-Brandt) model, ``distortion = [k1, k2, k3, k4]``:
    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, theta = atan(r)."""

    def _theta_d(self, theta: Array) -> tuple[Array, Array]:
        k1, k2, k3, k4 = self.distortion
        t2 = theta * theta
        value = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        deriv = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        return value, deriv

    def _radius_distort(self, r: Array) -> Array:
        return self._theta_d(np.arctan(r))[0]

    def _radius_undistort(self, r_d: Array) -> Array:
        theta = r_d.copy()
        for _ in range(UNDISTORT_NEWTON_ITERS):
            value, deriv = self._theta_d(theta)
            step = (value - r_d) / deriv
            theta = np.clip(theta - step, 0.0, np.pi / 2 - 1e-9)
            if np.nanmax(np.abs(step), initial=0.0) < 1e-15:
                break
        return np.tan(theta)


@register_camera("fov")
@dataclass(frozen=True)
class FovCamera(_RadialCamera):
    """FOV / ATAN model of PTAM and SVO, ``distortion = [omega]`` (radians):
    ``r_d = atan(2 r tan(omega / 2)) / omega``."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.distortion[0] < np.pi:
            raise CameraError(f"fov camera: omega must be in [0, pi), got {self.distortion[0]}")

    def _radius_distort(self, r: Array) -> Array:
        w = self.distortion[0]
        if w < 1e-9:
            return r.copy()
        return np.arctan(2.0 * r * np.tan(w / 2.0)) / w

    def _radius_undistort(self, r_d: Array) -> Array:
        w = self.distortion[0]
        if w < 1e-9:
            return r_d.copy()
        return np.tan(np.minimum(r_d * w, np.pi / 2 - 1e-9)) / (2.0 * np.tan(w / 2.0))
