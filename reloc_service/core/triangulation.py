"""Points from tracks of observations in posed views: two-view midpoint hypotheses on bearings
(so every camera model works), Levenberg-Marquardt refinement of the reprojection error in
pixels over all observations, and the rejection rules. Which keypoints form a track, and
landmarks lifted from depth maps, are :mod:`.landmarks`'s.

Rejection rules, applied to every new landmark: positive depth in every observing view
(cheirality, within ``[min_depth_m, max_depth_m]``), reprojection error below
``max_reprojection_px`` in every observing view, a parallax of at least ``min_parallax_deg``
between the new keyframe's ray and another view's ray, and a predicted depth uncertainty
below ``max_depth_uncertainty`` of the range. Pixel thresholds and residual weights scale
with each keypoint's pyramid level (:func:`keypoint_sigmas`).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from .cameras import Camera
from .errors import ConfigError
from .frame import Features

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class TriangulationConf:
    """Matching and rejection thresholds (pixels, metres, degrees in the names)."""

    #: Lowe ratio of the descriptor matching between two keyframes.
    ratio: float = 0.8
    #: Keep only mutual matches (each keypoint the other's nearest neighbour as well).
    mutual: bool = True
    #: Largest distance of a match to its epipolar line, pixels (checked as an angle on bearings).
    max_epipolar_px: float = 2.0
    #: Largest reprojection error in every observing view, pixels (times the keypoint's
    #: scale, see :func:`keypoint_sigmas`; the epipolar check is scaled likewise).
    max_reprojection_px: float = 2.0
    #: Smallest angle between the new keyframe's ray and another observing ray, degrees.
    #: 0: parallax matters only through the depth precision it buys, which the uncertainty
    #: gate below measures (stereo rigs and VIO keyframes a few centimetres apart make points
    #: of small parallax that are still precise enough to use).
    min_parallax_deg: float = 0.0
    #: Largest 1-sigma depth uncertainty of a new point along the new keyframe's ray, as a
    #: fraction of its range, from the refinement's information matrix with a localisation
    #: noise of ``keypoint_sigma_px`` times the keypoint's scale (short baselines and coarse
    #: keypoints make uncertain points). 1/3 keeps the 3-sigma depth interval in front of the
    #: camera, so the point's direction and side are certain: an uncertain point still
    #: constrains the rotation and, seen from near its keyframes, the position; the P3P inlier
    #: test and the verification judge how well it fits a query.
    max_depth_uncertainty: float = 1.0 / 3.0
    keypoint_sigma_px: float = 0.5
    #: Depth range accepted in every observing view, metres.
    min_depth_m: float = 0.05
    max_depth_m: float = 100.0
    #: Levenberg-Marquardt iterations of the point refinement.
    refine_iterations: int = 8
    #: Re-refine landmarks over all their observations when a keyframe extends their track.
    refine_tracks: bool = True
    #: Depth map sampling at a keypoint: "bilinear" or "nearest".
    depth_interpolation: str = "bilinear"
    #: Largest relative depth difference in the 2x2 pixels around a keypoint (discontinuity).
    max_depth_jump: float = 0.03

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise ConfigError(f"triangulation.ratio must be in (0, 1], got {self.ratio}")
        for name in ("max_epipolar_px", "max_reprojection_px", "min_depth_m", "max_depth_jump",
                     "max_depth_uncertainty", "keypoint_sigma_px"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"triangulation.{name} must be positive, got "
                                  f"{getattr(self, name)}")
        if not self.max_depth_m > self.min_depth_m:
            raise ConfigError(f"triangulation.max_depth_m ({self.max_depth_m}) must exceed "
                              f"min_depth_m ({self.min_depth_m})")
        if not 0 <= self.min_parallax_deg < 90:
            raise ConfigError(f"triangulation.min_parallax_deg must be in [0, 90), got "
                              f"{self.min_parallax_deg}")
        if self.refine_iterations < 0:
            raise ConfigError(f"triangulation.refine_iterations must be >= 0, got "
                              f"{self.refine_iterations}")
        if self.depth_interpolation not in ("bilinear", "nearest"):
            raise ConfigError(f"triangulation.depth_interpolation must be 'bilinear' or "
                              f"'nearest', got {self.depth_interpolation!r}")


class TrackStatus(enum.IntEnum):
    """Why a triangulated point was kept or rejected."""

    OK = 0
    DEGENERATE = 1     # fewer than two usable observations, or rays that do not intersect
    DEPTH = 2          # behind a camera (cheirality) or outside the depth range
    REPROJECTION = 3   # reprojection error too large in an observing view
    PARALLAX = 4       # rays too parallel for a reliable depth
    UNCERTAIN = 5      # depth too uncertain (short baseline for the keypoints' precision)


#: Scale step between pyramid levels of each detector: a keypoint found at level l is
#: localised about ``step ** l`` times less precisely than one at level 0.
LEVEL_SCALE_STEP = {"sift": 2.0, "orb": 1.2}


def keypoint_sigmas(features: Features) -> Array:
    """(N,) relative localisation noise of each keypoint: its level's scale, at least 1."""
    step = LEVEL_SCALE_STEP.get(features.kind, 1.0)
    return np.maximum(step ** features.levels.astype(np.float64), 1.0)


@dataclass(frozen=True, eq=False)
class ViewObservations:
    """Observations of some of P points in one view: ``point_index`` (M,) into the points
    (each point at most once per view), their ``pixels_px`` (M, 2) and the relative noise
    ``sigmas`` (M,) of each (residuals are divided by it; thresholds multiplied)."""

    camera: Camera
    cam_from_world: Array
    point_index: IntArray
    pixels_px: Array
    sigmas: Array = None  # type: ignore[assignment]  # default: ones

    def __post_init__(self) -> None:
        if self.sigmas is None:
            object.__setattr__(self, "sigmas", np.ones(len(self.point_index)))

    @property
    def centre_world(self) -> Array:
        """(3,) camera centre in the world frame."""
        return -self.cam_from_world[:3, :3].T @ self.cam_from_world[:3, 3]

    def subset(self, mask: npt.NDArray[np.bool_]) -> ViewObservations:
        return ViewObservations(self.camera, self.cam_from_world, self.point_index[mask],
                                self.pixels_px[mask], self.sigmas[mask])


@dataclass(eq=False)
class TrackResult:
    """Triangulated points (P, 3) world, their :class:`TrackStatus` (P,), their 1-sigma depth
    uncertainty (P,) along the reference view's ray in metres (inf where undetermined) and,
    per view, the mask of observations kept (the others were outliers of an accepted point or
    belong to a rejected point)."""

    points_world: Array
    status: npt.NDArray[np.int8]
    kept: list[npt.NDArray[np.bool_]]
    depth_sigmas_m: Array

    @property
    def accepted(self) -> npt.NDArray[np.bool_]:
        return self.status == TrackStatus.OK


@dataclass
class TriangulationStats:
    """What one keyframe's triangulation did (counts)."""

    matches: int = 0
    epipolar_inliers: int = 0
    extended: int = 0
    created: int = 0
    from_depth: int = 0
    refined: int = 0
    rejected: dict[str, int] = field(default_factory=dict)

    def merge(self, other: TriangulationStats) -> None:
        for name in ("matches", "epipolar_inliers", "extended", "created", "from_depth", "refined"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for key, value in other.rejected.items():
            self.rejected[key] = self.rejected.get(key, 0) + value


# -- geometry of bearings and points ----------------------------------------------------------

def rotate_points(points: Array, rotation: Array) -> Array:
    """(N, 3) @ rotation.T without BLAS (threaded BLAS is slow on (N, 3) x (3, 3))."""
    return np.einsum("nj,ij->ni", points, rotation)


def to_camera(cam_from_world: Array, points_world: Array) -> Array:
    """(N, 3) world points in the camera frame."""
    return rotate_points(points_world, cam_from_world[:3, :3]) + cam_from_world[:3, 3]


def epipolar_angles(bearings_a: Array, bearings_b: Array, b_from_a: Array) -> Array:
    """(M,) angular distance (radians) of matched unit bearings (M, 3) in cameras a and b from
    their epipolar planes, the larger of the two views' (a symmetric angular Sampson-like
    error). With no baseline, the angle between the rotated rays."""
    rotated = rotate_points(bearings_a, b_from_a[:3, :3])
    t = b_from_a[:3, 3]
    if np.linalg.norm(t) < 1e-9:
        return np.arccos(np.clip(np.einsum("ij,ij->i", rotated, bearings_b), -1.0, 1.0))
    t = t / np.linalg.norm(t)
    n_from_a = np.cross(t, rotated)          # epipolar plane normal, from a's ray
    n_from_b = np.cross(t, bearings_b)       # ... and from b's ray
    with np.errstate(invalid="ignore", divide="ignore"):
        sin_b = np.abs(np.einsum("ij,ij->i", bearings_b, n_from_a)) / np.linalg.norm(n_from_a,
                                                                                     axis=1)
        sin_a = np.abs(np.einsum("ij,ij->i", rotated, n_from_b)) / np.linalg.norm(n_from_b, axis=1)
    sin = np.nan_to_num(np.maximum(sin_a, sin_b), nan=1.0)
    return np.arcsin(np.clip(sin, 0.0, 1.0))


def _solve3(a: Array, b: Array) -> tuple[Array, npt.NDArray[np.bool_]]:
    """Solve (P, 3, 3) x = (P, 3) by the adjugate; (solution, solvable mask)."""
    cof = np.stack([np.cross(a[:, 1], a[:, 2]), np.cross(a[:, 2], a[:, 0]),
                    np.cross(a[:, 0], a[:, 1])], axis=1)       # rows of adj(a).T
    det = np.einsum("ij,ij->i", a[:, 0], cof[:, 0])
    scale = np.einsum("pij,pij->p", a, a) ** 1.5
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    safe = np.where(ok, det, 1.0)
    x = np.einsum("pji,pj->pi", cof, b) / safe[:, None]
    return np.where(ok[:, None], x, np.nan), ok


def triangulate_midpoint(views: Sequence[ViewObservations], num_points: int) -> Array:
    """(P, 3) world points closest (least squares) to all their observing rays; NaN where the
    rays do not determine a point (fewer than two, or parallel)."""
    a = np.zeros((num_points, 3, 3))
    b = np.zeros((num_points, 3))
    for v in views:
        dirs = rotate_points(v.camera.unproject(v.pixels_px), v.cam_from_world[:3, :3].T)
        proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]    # I - d d^T
        a[v.point_index] += proj
        b[v.point_index] += proj @ v.centre_world
    points, _ = _solve3(a, b)
    return points


def project_views(points_world: Array, views: Sequence[ViewObservations]
                  ) -> list[tuple[Array, Array]]:
    """Per view: pixels (M, 2) of its observed points (NaN behind the camera) and depths (M,)."""
    out = []
    for v in views:
        p_cam = to_camera(v.cam_from_world, points_world[v.point_index])
        out.append((v.camera.project(p_cam), p_cam[:, 2]))
    return out


def reprojection_errors(points_world: Array, views: Sequence[ViewObservations]) -> list[Array]:
    """Per view: (M,) reprojection errors in pixels; inf behind the camera or for NaN points."""
    return _errors_from(project_views(points_world, views), views)


def _errors_from(projections: list[tuple[Array, Array]], views: Sequence[ViewObservations]
                 ) -> list[Array]:
    errors = []
    for (px, _), v in zip(projections, views, strict=True):
        e = np.linalg.norm(px - v.pixels_px, axis=1)
        errors.append(np.where(np.isfinite(e), e, np.inf))
    return errors


def parallax_angles(points_world: Array, views: Sequence[ViewObservations]) -> Array:
    """(P,) largest angle (radians) between the ray of ``views[0]`` and the ray of any other
    view to each point; 0 for points ``views[0]`` does not observe."""
    n = len(points_world)
    ref = np.full((n, 3), np.nan)
    ref[views[0].point_index] = points_world[views[0].point_index] - views[0].centre_world
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    best = np.zeros(n)
    for v in views[1:]:
        ray = points_world[v.point_index] - v.centre_world
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        cos = np.clip(np.einsum("ij,ij->i", ray, ref[v.point_index]), -1.0, 1.0)
        angle = np.nan_to_num(np.arccos(cos), nan=0.0)
        best[v.point_index] = np.maximum(best[v.point_index], angle)
    return best


def depth_uncertainty(points_world: Array, views: Sequence[ViewObservations],
                      keypoint_sigma_px: float) -> Array:
    """(P,) 1-sigma uncertainty of each point along the ray of ``views[0]``, as a fraction of
    its range: ``sqrt(d^T C d) / range`` with ``C = keypoint_sigma_px^2 (J^T J)^-1`` (the
    residuals already divided by each observation's sigma). inf where undetermined."""
    h_mat, _ = _normal_equations(points_world, views)
    ray = points_world - views[0].centre_world
    rng = np.linalg.norm(ray, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = ray / rng[:, None]
        h_inv_d, ok = _solve3(h_mat, np.nan_to_num(d))
        var = keypoint_sigma_px**2 * np.einsum("pi,pi->p", d, h_inv_d)
        out = np.sqrt(np.maximum(var, 0.0)) / rng
    return np.where(ok & np.isfinite(out), out, np.inf)


# -- refinement -------------------------------------------------------------------------------

def _cost(points_world: Array, views: Sequence[ViewObservations], min_depth: float) -> Array:
    """(P,) sum of squared reprojection errors (each over its sigma); inf where a view sees
    the point behind it."""
    cost = np.zeros(len(points_world))
    for (px, depth), v in zip(project_views(points_world, views), views, strict=True):
        r2 = np.sum((px - v.pixels_px) ** 2, axis=1) / v.sigmas**2
        cost[v.point_index] += np.where(np.isfinite(r2) & (depth > min_depth), r2, np.inf)
    return np.where(np.isfinite(cost), cost, np.inf)


def _normal_equations(points_world: Array, views: Sequence[ViewObservations]
                      ) -> tuple[Array, Array]:
    """J^T J (P, 3, 3) and J^T r (P, 3) of the pixel residuals over their sigmas; the Jacobian
    of each camera model is taken by central differences in the camera frame (all models
    alike)."""
    h_mat = np.zeros((len(points_world), 3, 3))
    grad = np.zeros((len(points_world), 3))
    for v in views:
        p_cam = to_camera(v.cam_from_world, points_world[v.point_index])
        m = len(p_cam)
        step = 1e-6 * np.maximum(np.linalg.norm(p_cam, axis=1), 1e-3)
        offsets = np.zeros((7, m, 3))                 # 0, +x, -x, +y, -y, +z, -z
        for k in range(3):
            offsets[1 + 2 * k, :, k] = step
            offsets[2 + 2 * k, :, k] = -step
        px = v.camera.project((p_cam[None] + offsets).reshape(-1, 3)).reshape(7, m, 2)
        res = px[0] - v.pixels_px
        jac_cam = np.stack([(px[1 + 2 * k] - px[2 + 2 * k]) / (2 * step[:, None])
                            for k in range(3)], axis=2)                  # (M, 2, 3)
        jac = np.einsum("mik,kj->mij", jac_cam, v.cam_from_world[:3, :3]) / v.sigmas[:, None, None]
        res = res / v.sigmas[:, None]
        valid = np.isfinite(res).all(axis=1) & np.isfinite(jac).all(axis=(1, 2))
        jac[~valid] = 0.0
        res[~valid] = 0.0
        h_mat[v.point_index] += np.einsum("mki,mkj->mij", jac, jac)
        grad[v.point_index] += np.einsum("mki,mk->mi", jac, res)
    return h_mat, grad


def refine_points(points_world: Array, views: Sequence[ViewObservations], *, iterations: int = 8,
                  min_depth: float = 1e-6) -> Array:
    """(P, 3) points refined by Levenberg-Marquardt (one 3x3 system per point, all at once) on
    the reprojection error in pixels (over each observation's sigma) over all observations;
    a step is kept only where it lowers that point's error."""
    x = np.array(points_world, dtype=np.float64)
    if len(x) == 0:
        return x
    cost = _cost(x, views, min_depth)
    lam = np.full(len(x), 1e-4)
    for _ in range(iterations):
        h_mat, grad = _normal_equations(x, views)
        diag = np.einsum("pii->pi", h_mat)
        damped = h_mat + (lam[:, None] * np.maximum(diag, 1e-12))[:, :, None] * np.eye(3)[None]
        step, ok = _solve3(damped, -grad)
        trial = np.where(ok[:, None], x + step, x)
        trial_cost = _cost(trial, views, min_depth)
        better = ok & (trial_cost < cost)
        x[better] = trial[better]
        if not np.any(better & (trial_cost < cost * (1 - 1e-6) - 1e-12)):
            break                 # converged (or every step failed)
        cost = np.where(better, trial_cost, cost)
        lam = np.clip(np.where(better, lam * 0.2, lam * 10.0), 1e-9, 1e6)
    return x


# -- triangulation of tracks ------------------------------------------------------------------

def triangulate_tracks(views: Sequence[ViewObservations], num_points: int,
                       conf: TriangulationConf) -> TrackResult:
    """Triangulate P points observed in ``views`` (``views[0]`` is the reference, the new
    keyframe, and must observe every point): the best two-view midpoint hypothesis (the one
    most observations agree with), refinement over the observations that agree, a second
    round re-admitting observations that fit the refined point, then the rejection rules."""
    x, first_bad_depth = _two_view_hypotheses(views, num_points, conf)
    for _ in range(2):
        bad_depth, bad_reproj = observation_faults(x, views, conf)
        inlier_views = [v.subset(~(d | r))
                        for v, d, r in zip(views, bad_depth, bad_reproj, strict=True)]
        x = refine_points(x, inlier_views, iterations=conf.refine_iterations,
                          min_depth=conf.min_depth_m)
    uncertainty = depth_uncertainty(x, inlier_views, conf.keypoint_sigma_px)
    status = _classify(x, views, inlier_views, first_bad_depth, uncertainty, conf)
    ok = status == TrackStatus.OK
    in_any = [np.isin(v.point_index, iv.point_index)
              for v, iv in zip(views, inlier_views, strict=True)]
    kept = [k & ok[v.point_index] for v, k in zip(views, in_any, strict=True)]
    with np.errstate(invalid="ignore"):
        sigmas = uncertainty * np.linalg.norm(x - views[0].centre_world, axis=1)
    return TrackResult(points_world=x, status=status, kept=kept,
                       depth_sigmas_m=np.where(np.isfinite(sigmas), sigmas, np.inf))


def _two_view_hypotheses(views: Sequence[ViewObservations], num_points: int,
                         conf: TriangulationConf) -> tuple[Array, list[npt.NDArray[np.bool_]]]:
    """Per point, the midpoint of the reference ray and one other view's ray that the most
    observations agree with (ties: the smaller squared error), so that one bad match among
    several views does not spoil the point; and the depth faults at that point."""
    best = np.full((num_points, 3), np.nan)
    best_count = np.full(num_points, -1)
    best_cost = np.full(num_points, np.inf)
    for v in views[1:]:
        ref = views[0].subset(np.isin(views[0].point_index, v.point_index))
        x = triangulate_midpoint([ref, v], num_points)
        bad_depth, bad_reproj = observation_faults(x, views, conf)
        count = np.zeros(num_points, np.int64)
        cost = np.zeros(num_points)
        errors = reprojection_errors(x, views)
        for w, e, d, r in zip(views, errors, bad_depth, bad_reproj, strict=True):
            good = ~(d | r)
            count[w.point_index[good]] += 1
            cost[w.point_index[good]] += (e[good] / w.sigmas[good]) ** 2
        better = np.isfinite(x).all(axis=1) & ((count > best_count)
                                               | ((count == best_count) & (cost < best_cost)))
        best[better], best_count[better], best_cost[better] = x[better], count[better], cost[better]
    bad_depth, _ = observation_faults(best, views, conf)
    return best, bad_depth


def observation_faults(points_world: Array, views: Sequence[ViewObservations],
                        conf: TriangulationConf) -> tuple[list[npt.NDArray[np.bool_]],
                                                          list[npt.NDArray[np.bool_]]]:
    """Per view: observations with a bad depth (cheirality or range) and with a reprojection
    error over the threshold."""
    projections = project_views(points_world, views)
    errors = _errors_from(projections, views)
    with np.errstate(invalid="ignore"):
        bad_depth = [~((d >= conf.min_depth_m) & (d <= conf.max_depth_m)) for _, d in projections]
    bad_reproj = [e > conf.max_reprojection_px * v.sigmas
                  for e, v in zip(errors, views, strict=True)]
    return bad_depth, bad_reproj


def _classify(points_world: Array, views: Sequence[ViewObservations],
              inlier_views: Sequence[ViewObservations],
              first_bad_depth: list[npt.NDArray[np.bool_]], uncertainty: Array,
              conf: TriangulationConf) -> npt.NDArray[np.int8]:
    """:class:`TrackStatus` (P,) of the refined points over their inlier observations, given
    their relative depth ``uncertainty`` (P,) (:func:`depth_uncertainty`)."""
    n = len(points_world)
    status = np.zeros(n, np.int8)
    count = np.zeros(n, np.int64)
    ref_kept = np.zeros(n, bool)
    ref_kept[inlier_views[0].point_index] = True
    for v in inlier_views:
        count[v.point_index] += 1
    any_bad_depth = np.zeros(n, bool)
    for v, bad in zip(views, first_bad_depth, strict=True):
        any_bad_depth[v.point_index[bad]] = True
    bad_depth, bad_reproj = observation_faults(points_world, inlier_views, conf)
    final_depth, final_reproj = np.zeros(n, bool), np.zeros(n, bool)
    for v, d, r in zip(inlier_views, bad_depth, bad_reproj, strict=True):
        final_depth[v.point_index[d]] = True
        final_reproj[v.point_index[r]] = True
    parallax = parallax_angles(points_world, inlier_views)
    lost = ~ref_kept | (count < 2)
    # Later rules first: the first failing rule in (degenerate, depth, reprojection, parallax,
    # uncertain) order wins.
    with np.errstate(invalid="ignore"):
        status[~(uncertainty <= conf.max_depth_uncertainty)] = TrackStatus.UNCERTAIN
    status[parallax < np.deg2rad(conf.min_parallax_deg)] = TrackStatus.PARALLAX
    status[final_reproj | (lost & ~any_bad_depth)] = TrackStatus.REPROJECTION
    status[final_depth | (lost & any_bad_depth)] = TrackStatus.DEPTH
    status[~np.isfinite(points_world).all(axis=1)] = TrackStatus.DEGENERATE
    return status
