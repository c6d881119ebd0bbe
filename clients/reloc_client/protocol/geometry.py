"""Pose and camera wire types: quaternion helpers, WirePose and WireCamera."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .checks import _UNLIMITED, Array, ErrorCode, _fail, _Fields, _float, _int, _list, _numbers, _str

#: Camera models and their accepted numbers of distortion values (reloc_service.core.cameras).
CAMERA_MODELS: dict[str, tuple[int, ...]] = {
    "pinhole": (0,), "radtan": (4, 5), "equidistant": (4,), "fov": (1,)}

QUAT_NORM_TOL = 1e-3
ROTATION_TOL = 1e-5
#: A pose covariance is symmetric when no entry differs from its mirror by more than this
#: share of the largest entry (float64 products such as ``G C G^T`` leave ~1e-16), and
#: positive semi-definite when no eigenvalue is below minus this share of the largest one
#: (the rounding of an eigendecomposition); :data:`COVARIANCE_ABS_TOL` (a nanometre, a
#: nanoradian squared) where every entry is about zero.
COVARIANCE_REL_TOL = 1e-9
COVARIANCE_ABS_TOL = 1e-18


def quat_xyzw_to_rotation(q: npt.ArrayLike) -> Array:
    """Unit quaternions (..., 4) (x, y, z, w), Hamilton, to (..., 3, 3) rotation matrices.

    The one quaternion implementation of reloc (``reloc_service.core.geometry`` validates and calls
    it); NumPy only, so the client can use it too. ``q`` must already have unit norm."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def rotation_to_quat_xyzw_array(r: npt.ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) to unit quaternions (..., 4) (x, y, z, w) with w >= 0.

    Shepperd's method: divide by the largest of |w|, |x|, |y|, |z| (read off the trace and the
    diagonal), which is numerically safe for every rotation."""
    m = np.asarray(r, dtype=np.float64)
    d0, d1, d2 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 |q_i|^2 for i = w, x, y, z; every one of the four formulas below is exact, the largest
    # is the best conditioned.
    four_sq = np.stack([1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2])
    s = 2.0 * np.sqrt(np.maximum(four_sq, 0.0))  # 4 |q_i|
    a = m[..., 2, 1] - m[..., 1, 2]
    b = m[..., 0, 2] - m[..., 2, 0]
    c = m[..., 1, 0] - m[..., 0, 1]
    xy, xz, yz = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = np.stack([  # (4 branches, 4 components x y z w, ...)
            np.stack([a / s[0], b / s[0], c / s[0], s[0] / 4]),
            np.stack([s[1] / 4, xy / s[1], xz / s[1], a / s[1]]),
            np.stack([xy / s[2], s[2] / 4, yz / s[2], b / s[2]]),
            np.stack([xz / s[3], yz / s[3], s[3] / 4, c / s[3]])])
    # The w branch wins ties, as trace >= max(diagonal) in the scalar form of the method.
    best = np.argmax(four_sq, axis=0)
    q = np.take_along_axis(candidates, best[None, None], axis=0)[0]
    q = np.moveaxis(q, 0, -1)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0, -q, q)


def rotation_to_quat_xyzw(r: npt.ArrayLike) -> tuple[float, float, float, float]:
    """(3, 3) rotation matrix to a unit quaternion (x, y, z, w) with w >= 0."""
    x, y, z, w = rotation_to_quat_xyzw_array(r).tolist()
    return (x, y, z, w)


def pose_covariance_problem(covariance: npt.ArrayLike) -> str | None:
    """Why ``covariance`` is not a pose covariance, or None when it is one: a (6, 6) finite,
    symmetric, positive semi-definite matrix (twist (rho, omega), right perturbation, metres
    and radians; tolerances :data:`COVARIANCE_REL_TOL`). The one definition the wire decoder,
    the keyframe and the snapshot check share."""
    try:
        c = np.asarray(covariance, dtype=np.float64)
    except (TypeError, ValueError):
        return "not an array of numbers"
    if c.shape != (6, 6):
        return f"shape {c.shape}; expected (6, 6)"
    if not np.all(np.isfinite(c)):
        return "NaN or infinite entries"
    scale = float(np.abs(c).max())
    asymmetry = float(np.abs(c - c.T).max())
    if asymmetry > COVARIANCE_REL_TOL * scale + COVARIANCE_ABS_TOL:
        return f"not symmetric (|C - C^T| = {asymmetry:.3g}, largest entry {scale:.3g})"
    eigenvalues = np.linalg.eigvalsh(0.5 * (c + c.T))
    if eigenvalues[0] < -(COVARIANCE_REL_TOL * max(eigenvalues[-1], 0.0) + COVARIANCE_ABS_TOL):
        return (f"not positive semi-definite (smallest eigenvalue {eigenvalues[0]:.3g}, "
                f"largest {eigenvalues[-1]:.3g})")
    return None


@dataclass(frozen=True)
class WirePose:
    """A pose ``a_from_b`` on the wire: translation ``t`` (metres) and unit quaternion ``q``
    (x, y, z, w, Hamilton). Messages carry ``world_from_cam`` (camera x right, y down, z
    forward)."""

    t: tuple[float, float, float]
    q: tuple[float, float, float, float]

    @classmethod
    def from_matrix(cls, a_from_b: npt.ArrayLike, path: str = "world_from_cam") -> WirePose:
        """From a (4, 4) homogeneous pose; ProtocolError(BAD_POSE) unless finite with an
        orthonormal rotation (det +1) and last row [0 0 0 1]."""
        m = np.asarray(a_from_b, dtype=np.float64)
        if m.shape != (4, 4):
            raise _fail(ErrorCode.BAD_POSE, path, "a (4, 4) pose", f"shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise _fail(ErrorCode.BAD_POSE, path, "finite values", "NaN or Inf")
        r = m[:3, :3]
        ortho = float(np.abs(r @ r.T - np.eye(3)).max())
        if ortho > ROTATION_TOL or np.linalg.det(r) <= 0:
            raise _fail(ErrorCode.BAD_POSE, path, "an orthonormal rotation with det +1",
                        f"|R R^T - I| = {ortho:.2e}, det = {np.linalg.det(r):.3f}")
        if np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise _fail(ErrorCode.BAD_POSE, path, "last row [0 0 0 1]", m[3].tolist())
        t = m[:3, 3]
        return cls((float(t[0]), float(t[1]), float(t[2])), rotation_to_quat_xyzw(r))

    @classmethod
    def from_tq(cls, t: Sequence[float], q: Sequence[float],
                path: str = "world_from_cam") -> WirePose:
        """From translation (3,) and quaternion (x, y, z, w); normalises q (norm within 1e-3)."""
        return cls.from_wire({"t": list(t), "q": list(q)}, path)

    def matrix(self) -> Array:
        """(4, 4) float64 homogeneous pose."""
        m = np.eye(4)
        m[:3, :3] = quat_xyzw_to_rotation(self.q)
        m[:3, 3] = self.t
        return m

    def to_wire(self) -> dict[str, Any]:
        return {"t": list(self.t), "q": list(self.q)}

    @classmethod
    def from_wire(cls, value: Any, path: str) -> WirePose:
        f = _Fields(value, path)
        t = f.req("t", lambda v, p: _numbers(v, p, 3, ErrorCode.BAD_POSE))
        q = f.req("q", lambda v, p: _numbers(v, p, 4, ErrorCode.BAD_POSE))
        f.done()
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise _fail(ErrorCode.BAD_POSE, f"{path}.q",
                        f"a unit quaternion x y z w (norm 1 within {QUAT_NORM_TOL:g})",
                        f"norm {norm:.6f}")
        qn = (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
        return cls((t[0], t[1], t[2]), qn)


@dataclass(frozen=True)
class WireCamera:
    """The dataset camera dict: ``model`` (see CAMERA_MODELS), image size (px), focal lengths
    and principal point (px, pixel centres at integer coordinates), distortion values."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], path: str = "camera") -> WireCamera:
        """Validate a camera dict (e.g. ``Camera.to_dict()`` or a ``cameras.json`` entry)."""
        return cls.from_wire(dict(d), path)

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height,
                "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "distortion": list(self.distortion)}

    to_wire = to_dict

    @classmethod
    def from_wire(cls, value: Any, path: str) -> WireCamera:
        f = _Fields(value, path)
        model = f.req("model", lambda v, p: _str(v, p, _UNLIMITED))
        size = [f.req(n, lambda v, p: _camera_int(v, p)) for n in ("width", "height")]
        intr = [f.req(n, _float) for n in ("fx", "fy", "cx", "cy")]
        dist = f.opt("distortion", lambda v, p: _list(v, p, _UNLIMITED, _float), ())
        f.done()
        if model not in CAMERA_MODELS:
            raise _fail(ErrorCode.BAD_CAMERA, f"{path}.model", f"one of {sorted(CAMERA_MODELS)}",
                        model)
        if intr[0] <= 0 or intr[1] <= 0:
            raise _fail(ErrorCode.BAD_CAMERA, path, "positive fx and fy", intr[:2])
        if len(dist) not in CAMERA_MODELS[model]:
            counts = " or ".join(map(str, CAMERA_MODELS[model]))
            raise _fail(ErrorCode.BAD_CAMERA, f"{path}.distortion",
                        f"{counts} values for model {model!r}", f"{len(dist)} values")
        fx, fy, cx, cy = intr
        return cls(model, size[0], size[1], fx, fy, cx, cy, tuple(dist))


def _camera_int(v: Any, p: str) -> int:
    n = _int(v, p)
    if n <= 0:
        raise _fail(ErrorCode.BAD_CAMERA, p, "a positive integer", v)
    return n
