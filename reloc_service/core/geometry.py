"""SE(3)/SO(3) helpers: 4x4 homogeneous poses, quaternions (x y z w, Hamilton), exp/log, errors.

Poses are named after their frames: ``a_from_b`` maps points in frame b to frame a, and
compose as ``a_from_c = a_from_b @ b_from_c``. The map convention is ``world_from_cam``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from reloc_client.protocol.geometry import (
    pose_covariance_problem,
    quat_xyzw_to_rotation,
    rotation_to_quat_xyzw_array,
)
from scipy.spatial.transform import Rotation

from .errors import GeometryError

Array = npt.NDArray[np.float64]

_ORTHO_TOL = 1e-6
_EYE3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
#: np.allclose(row, _LAST_ROW, atol=1e-9)'s bound (atol + rtol * |b|), compared directly:
#: allclose's generic path cost more than the rest of check_pose (1000 keyframes per load).
_LAST_ROW_TOL = 1e-9 + 1e-5 * np.abs(_LAST_ROW)


def check_rotation(rotation: npt.ArrayLike, *, name: str = "rotation", tol: float = _ORTHO_TOL) -> Array:
    """Return ``rotation`` as float64 (3, 3) after checking it is finite, orthonormal, det +1."""
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3):
        raise GeometryError(f"{name}: expected a (3, 3) rotation matrix, got shape {r.shape}")
    if not np.isfinite(r).all():
        raise GeometryError(f"{name}: rotation has non-finite entries")
    err = np.abs(r @ r.T - _EYE3).max()
    if err > tol or _det3(r) < 0:
        raise GeometryError(f"{name}: not a proper rotation (|R R^T - I| = {err:.2e}, det = "
                            f"{np.linalg.det(r):.3f}); expected orthonormal with det +1")
    return r


def _det3(r: Array) -> float:
    """Determinant of a 3x3 by cofactors on Python floats (np.linalg.det's LU call costs
    more than the whole orthonormality test for one small matrix)."""
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()
    return float(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g))


def check_pose(pose: npt.ArrayLike, *, name: str = "world_from_cam", tol: float = _ORTHO_TOL) -> Array:
    """Return ``pose`` as float64 (4, 4) after checking finite values, a proper rotation and
    a last row of ``[0, 0, 0, 1]``; raise :class:`GeometryError` naming ``name`` otherwise."""
    t = np.asarray(pose, dtype=np.float64)
    if t.shape != (4, 4):
        raise GeometryError(f"{name}: expected a (4, 4) homogeneous pose, got shape {t.shape}")
    if not np.isfinite(t).all():
        raise GeometryError(f"{name}: pose has non-finite entries")
    if not (np.abs(t[3] - _LAST_ROW) <= _LAST_ROW_TOL).all():
        raise GeometryError(f"{name}: last row must be [0 0 0 1], got {t[3].tolist()}")
    check_rotation(t[:3, :3], name=name, tol=tol)
    return t


def check_pose_covariance(covariance: npt.ArrayLike, *, name: str = "pose_covariance") -> Array:
    """Return ``covariance`` as a float64 (6, 6) symmetric matrix (mirrored to exact symmetry)
    after checking it is a pose covariance: finite, symmetric and positive semi-definite
    (:func:`reloc_client.protocol.pose_covariance_problem`); :class:`GeometryError` naming
    ``name`` and the problem otherwise."""
    problem = pose_covariance_problem(covariance)
    if problem is not None:
        raise GeometryError(f"{name}: expected a 6x6 pose covariance (symmetric, positive "
                            f"semi-definite; twist (rho, omega), m and rad): {problem}")
    c = np.asarray(covariance, dtype=np.float64)
    return 0.5 * (c + c.T)


def pose_covariance_from_sigmas(position_sigma_m: float, rotation_sigma_rad: float) -> Array:
    """(6, 6) diagonal pose covariance: ``position_sigma_m`` on each translation axis,
    ``rotation_sigma_rad`` about each rotation axis (twist (rho, omega))."""
    return np.diag([position_sigma_m**2] * 3 + [rotation_sigma_rad**2] * 3).astype(np.float64)


def check_points(points: npt.ArrayLike, *, name: str = "points", dim: int = 3) -> Array:
    """Return ``points`` as float64 (N, dim), checking the shape (values may be NaN)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != dim:
        raise GeometryError(f"{name}: expected shape (N, {dim}), got {p.shape}")
    return p


def quat_xyzw_to_matrix(q_xyzw: npt.ArrayLike) -> Array:
    """Unit quaternion (x, y, z, w), Hamilton convention, to a (3, 3) rotation matrix.

    The quaternion is normalised; a zero or non-finite quaternion raises GeometryError."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise GeometryError(f"quaternion: expected 4 finite values x y z w, got {q!r}")
    n = np.linalg.norm(q)
    if n < 1e-12:
        raise GeometryError("quaternion: zero norm")
    if abs(n - 1.0) > 1e-3:
        raise GeometryError(f"quaternion: expected unit norm, got {n:.6f}")
    return quat_xyzw_to_rotation(q / n)


def matrix_to_quat_xyzw(rotation: npt.ArrayLike) -> Array:
    """(3, 3) rotation matrix to a unit quaternion (x, y, z, w) with w >= 0."""
    return rotation_to_quat_xyzw_array(check_rotation(rotation, tol=1e-5))


def pose_from_tq(t_xyz: npt.ArrayLike, q_xyzw: npt.ArrayLike) -> Array:
    """Translation (3,) and quaternion (x y z w) to a (4, 4) pose ``a_from_b``."""
    t = np.asarray(t_xyz, dtype=np.float64)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise GeometryError(f"translation: expected 3 finite values, got {t!r}")
    out = np.eye(4)
    out[:3, :3] = quat_xyzw_to_matrix(q_xyzw)
    out[:3, 3] = t
    return out


def pose_to_tq(pose: npt.ArrayLike) -> tuple[Array, Array]:
    """(4, 4) pose to (translation (3,), quaternion x y z w (4,))."""
    p = np.asarray(pose, dtype=np.float64)
    return p[:3, 3].copy(), matrix_to_quat_xyzw(p[:3, :3])


def pose_from_tum(values: npt.ArrayLike) -> Array:
    """``tx ty tz qx qy qz qw`` (7,) to a (4, 4) pose."""
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (7,):
        raise GeometryError(f"pose: expected 7 values tx ty tz qx qy qz qw, got {v.shape}")
    return pose_from_tq(v[:3], v[3:])


def pose_to_tum(pose: npt.ArrayLike) -> Array:
    """(4, 4) pose to ``tx ty tz qx qy qz qw`` (7,)."""
    t, q = pose_to_tq(pose)
    return np.concatenate([t, q])


def invert(a_from_b: npt.ArrayLike) -> Array:
    """Inverse of a rigid transform: returns ``b_from_a``."""
    p = np.asarray(a_from_b, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = p[:3, :3].T
    out[:3, 3] = -p[:3, :3].T @ p[:3, 3]
    return out


def compose(a_from_b: npt.ArrayLike, b_from_c: npt.ArrayLike) -> Array:
    """``a_from_c = a_from_b @ b_from_c``."""
    return np.asarray(a_from_b, dtype=np.float64) @ np.asarray(b_from_c, dtype=np.float64)


def transform_points(a_from_b: npt.ArrayLike, points_b: npt.ArrayLike) -> Array:
    """Map (N, 3) points from frame b to frame a."""
    p = np.asarray(a_from_b, dtype=np.float64)
    return check_points(points_b) @ p[:3, :3].T + p[:3, 3]


def skew(v: npt.ArrayLike) -> Array:
    """(3,) vector to its (3, 3) cross-product matrix."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _compiled_rotation_kernels() -> Any:
    """SciPy's compiled rotation module (what ``Rotation`` runs for NumPy input, SciPy >= 1.16),
    if it is there and gives ``Rotation``'s own matrices on a check vector; else None. It is
    private API: any change of it (missing, renamed, other signature or values) means None,
    and :func:`so3_exp` uses ``Rotation`` itself."""
    try:
        from scipy.spatial.transform import _rotation_cy as kernels

        v = np.array([0.3, -1.2, 2.1])
        matrix = kernels.as_matrix(kernels.from_rotvec(v)[None, :])[0]
        if np.array_equal(matrix, Rotation.from_rotvec(v).as_matrix()):
            return kernels
    except Exception:  # noqa: BLE001 - private API: whatever it does, fall back
        pass
    return None


_rotation_kernels = _compiled_rotation_kernels()


def so3_exp(omega: npt.ArrayLike) -> Array:
    """Rotation vector (3,) (axis * angle, radians) to a (3, 3) rotation matrix:
    ``Rotation.from_rotvec(omega).as_matrix()``, by the compiled functions that runs where
    SciPy has them (the same values, without its array-API dispatch: about 3 instead of 9
    microseconds, and P3P's refinement takes one per query)."""
    v = np.asarray(omega, dtype=np.float64)
    if _rotation_kernels is not None and v.shape == (3,):
        matrix: Array = _rotation_kernels.as_matrix(_rotation_kernels.from_rotvec(v)[None, :])[0]
        return matrix
    return Rotation.from_rotvec(v).as_matrix()


def so3_log(rotation: npt.ArrayLike) -> Array:
    """(3, 3) rotation matrix to its rotation vector (3,), angle in [0, pi]."""
    return Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_rotvec()


def _left_jacobian(omega: Array) -> Array:
    theta = np.linalg.norm(omega)
    k = skew(omega)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * k
    return (np.eye(3) + (1 - np.cos(theta)) / theta**2 * k
            + (theta - np.sin(theta)) / theta**3 * (k @ k))


def se3_exp(xi: npt.ArrayLike) -> Array:
    """Twist ``xi = (rho, omega)`` (6,) to a (4, 4) pose (translation part first)."""
    v = np.asarray(xi, dtype=np.float64)
    if v.shape != (6,):
        raise GeometryError(f"twist: expected shape (6,), got {v.shape}")
    out = np.eye(4)
    out[:3, :3] = so3_exp(v[3:])
    out[:3, 3] = _left_jacobian(v[3:]) @ v[:3]
    return out


def _left_jacobians(omega: Array) -> Array:
    """(K, 3, 3) :func:`_left_jacobian` of (K, 3) rotation vectors: ``I + (1 - cos t) / t^2 K
    + (t - sin t) / t^3 K^2``, and ``I + K / 2`` for a rotation too small for those
    quotients."""
    theta = np.sqrt((omega * omega).sum(axis=1))
    k = np.zeros((len(omega), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -omega[:, 2], omega[:, 1], -omega[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = omega[:, 2], -omega[:, 1], omega[:, 0]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    c1 = np.where(small, 0.5, (1 - np.cos(safe)) / safe**2)
    c2 = np.where(small, 0.0, (safe - np.sin(safe)) / safe**3)
    out: Array = np.eye(3) + c1[:, None, None] * k + c2[:, None, None] * (k @ k)
    return out


def se3_exp_many(xi: npt.ArrayLike) -> Array:
    """(K, 6) twists ``(rho, omega)`` to (K, 4, 4) poses: :func:`se3_exp` of each row (the
    same formula vectorised, so equal to rounding)."""
    v = np.asarray(xi, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 6:
        raise GeometryError(f"twists: expected shape (K, 6), got {v.shape}")
    out = np.zeros((len(v), 4, 4))
    if _rotation_kernels is not None and len(v):
        # Rotation's own compiled functions (as so3_exp): the same matrices, without the
        # array-API dispatch that cost most of a call (about 20 against 2 microseconds for
        # the intrinsics test's seven starts, a few calls per tracked query).
        omega = np.ascontiguousarray(v[:, 3:])
        out[:, :3, :3] = _rotation_kernels.as_matrix(_rotation_kernels.from_rotvec(omega))
    else:
        out[:, :3, :3] = Rotation.from_rotvec(v[:, 3:]).as_matrix()
    out[:, :3, 3] = np.einsum("kij,kj->ki", _left_jacobians(v[:, 3:]), v[:, :3])
    out[:, 3, 3] = 1.0
    return out


def se3_log_many(poses: npt.ArrayLike) -> Array:
    """(K, 4, 4) poses to their (K, 6) twists: :func:`se3_log` of each (the rotation vectors
    the same, the translations equal to rounding), in one call of SciPy's compiled rotation
    functions where it has them (one ``Rotation`` costs more than the arithmetic)."""
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise GeometryError(f"poses: expected shape (K, 4, 4), got {p.shape}")
    if len(p) == 0:
        return np.zeros((0, 6))
    rotations = np.ascontiguousarray(p[:, :3, :3])
    if _rotation_kernels is not None:
        omega = np.asarray(_rotation_kernels.as_rotvec(_rotation_kernels.from_matrix(rotations)))
    else:
        omega = Rotation.from_matrix(rotations).as_rotvec()
    rho = np.linalg.solve(_left_jacobians(omega), p[:, :3, 3, None])[:, :, 0]
    return np.concatenate([rho, omega], axis=1)


def se3_log(pose: npt.ArrayLike) -> Array:
    """(4, 4) pose to its twist ``(rho, omega)`` (6,); inverse of :func:`se3_exp`."""
    p = np.asarray(pose, dtype=np.float64)
    omega = so3_log(p[:3, :3])
    rho = np.linalg.solve(_left_jacobian(omega), p[:3, 3])
    return np.concatenate([rho, omega])


def se3_adjoint(a_from_b: npt.ArrayLike) -> Array:
    """(6, 6) adjoint of a pose for twists ``(rho, omega)``: ``a_from_b @ exp(xi) @ b_from_a
    = exp(Ad xi)``, ``Ad = [[R, [t]x R], [0, R]]``. A right perturbation ``xi`` of
    ``world_from_b`` seen as a right perturbation of ``world_from_a`` (with
    ``a_from_b = inv(world_from_a) @ world_from_b``) is ``Ad(a_from_b) xi``."""
    p = np.asarray(a_from_b, dtype=np.float64)
    r, t = p[:3, :3], p[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = r
    out[:3, 3:] = skew(t) @ r
    out[3:, 3:] = r
    return out


def se3_adjoints(a_from_b: npt.ArrayLike) -> Array:
    """(K, 6, 6) :func:`se3_adjoint` of (K, 4, 4) poses at once."""
    p = np.asarray(a_from_b, dtype=np.float64).reshape(-1, 4, 4)
    r, t = p[:, :3, :3], p[:, :3, 3]
    x, y, z = t[:, 0], t[:, 1], t[:, 2]
    zero = np.zeros_like(x)
    t_skew = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1),
                       np.stack([-y, x, zero], -1)], -2)
    out = np.zeros((len(p), 6, 6))
    out[:, :3, :3] = r
    out[:, :3, 3:] = t_skew @ r
    out[:, 3:, 3:] = r
    return out


def rotation_angle(rotation: npt.ArrayLike) -> float:
    """Angle (radians, in [0, pi]) of a rotation matrix, robust near 0 and pi."""
    r = np.asarray(rotation, dtype=np.float64)
    return float(np.linalg.norm(so3_log(r)))


def pose_error(world_from_cam_est: npt.ArrayLike, world_from_cam_gt: npt.ArrayLike) -> tuple[float, float]:
    """Translation error (metres, between camera centres) and rotation error (radians)."""
    est = np.asarray(world_from_cam_est, dtype=np.float64)
    gt = np.asarray(world_from_cam_gt, dtype=np.float64)
    dt = float(np.linalg.norm(est[:3, 3] - gt[:3, 3]))
    dr = rotation_angle(est[:3, :3].T @ gt[:3, :3])
    return dt, dr


def look_at(eye: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0)) -> Array:
    """``world_from_cam`` of a camera at ``eye`` looking at ``target`` (camera x right, y down,
    z forward) with the image's up direction as close to ``up`` as possible."""
    eye_w = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye_w
    if np.linalg.norm(z) < 1e-12:
        raise GeometryError("look_at: eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise GeometryError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    out = np.eye(4)
    out[:3, :3] = np.column_stack([x, y, z])
    out[:3, 3] = eye_w
    return out
