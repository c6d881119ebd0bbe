"""Pose and camera wire types: quaternion helpers, WirePose and WireCamera."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .checks import _UNLIMITED, Array, ErrorCode, _fail, _Fields, _float, _int, _list, _numbers, _str

#: Camera models and their accepted numbers of distortion values (reloc_service.cameras).
CAMERA_MODELS: dict[str, tuple[int, ...]] = {
    "pinhole": (0,), "radtan": (4, 5), "equidistant": (4,), "fov": (1,)}

QUAT_NORM_TOL = 1e-3
ROTATION_TOL = 1e-5


def quat_xyzw_to_rotation(q: Sequence[float]) -> Array:
    """Unit quaternion (x, y, z, w), Hamilton, to a (3, 3) rotation matrix."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rotation_to_quat_xyzw(r: Array) -> tuple[float, float, float, float]:
    """(3, 3) rotation matrix to a unit quaternion (x, y, z, w) with w >= 0 (Shepperd)."""
    diag = np.array([r[0, 0], r[1, 1], r[2, 2]])
    trace = diag.sum()
    # Pick the largest of (w, x, y, z) to divide by: numerically safe for every rotation.
    if trace >= diag.max():
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(diag))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 0.0))
        q = [0.0, 0.0, 0.0, (r[k, j] - r[j, k]) / s]
        q[i], q[j], q[k] = s / 4, (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s
    qa = np.array(q) / np.linalg.norm(q)
    qa = qa if qa[3] >= 0 else -qa
    return (float(qa[0]), float(qa[1]), float(qa[2]), float(qa[3]))


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
