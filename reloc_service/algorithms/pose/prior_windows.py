"""Search windows from a pose prior and its covariance: each landmark's projection under the
prior and, to first order, the 2x2 covariance of that projection
(``J C J^T + sigma^2 I``, ``J`` the pixel's Jacobian w.r.t. a right perturbation of
``world_from_cam``, ``C`` the prior's 6x6 covariance, ``sigma`` the keypoint noise and the
landmark's own depth uncertainty as seen from the prior). A query keypoint may match a
landmark only inside the landmark's chi-square gate ``d^T S^-1 d <= chi2_2(p)``; the
descriptor test is then the one guided matching uses (:mod:`.guided`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.frame import Features
from ...core.geometry import invert, transform_points
from .guided import _one_to_one, background_distance, project_into
from .point_uncertainty import PointUncertainty
from .prior_match import gated_best
from .projection import pose_jacobian

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class Windows:
    """Per landmark row of a pool: ``px`` (L, 2) its projection under the prior,
    ``inv_cov`` (L, 2, 2) the inverse of its projection's covariance, ``radius_px`` (L,)
    the gate's half major axis, ``area_px`` (L,) the gate's area, ``visible`` (L,) whether
    it projects in front of the camera and inside the image."""

    px: Array
    inv_cov: Array
    radius_px: Array
    area_px: Array
    visible: npt.NDArray[np.bool_]


def predict_windows(camera: Camera, world_from_cam: Array, covariance: Array,
                    points_world: Array, gate_chi2: float, pixel_sigmas: Array
                    ) -> Windows:
    """:class:`Windows` of (L, 3) world points seen from the prior ``world_from_cam`` with
    its (6, 6) ``covariance``; ``pixel_sigmas`` (L,) the isotropic noise each projection
    carries besides the prior's (keypoint localisation, landmark depth)."""
    px, visible = project_into(camera, world_from_cam, points_world)
    n = len(points_world)
    inv_cov = np.zeros((n, 2, 2))
    radius = np.full(n, np.inf)
    area = np.full(n, np.inf)
    rows = np.flatnonzero(visible)
    if len(rows):
        points_cam = transform_points(invert(world_from_cam), points_world[rows])
        jac = pose_jacobian(camera, points_cam).reshape(len(rows), 2, 6)
        cov = jac @ covariance @ jac.transpose(0, 2, 1)
        cov[:, 0, 0] += pixel_sigmas[rows] ** 2
        cov[:, 1, 1] += pixel_sigmas[rows] ** 2
        a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
        det = a * c - b * b
        inv = np.empty_like(cov)
        inv[:, 0, 0], inv[:, 1, 1] = c / det, a / det
        inv[:, 0, 1] = inv[:, 1, 0] = -b / det
        largest = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)
        inv_cov[rows] = inv
        radius[rows] = np.sqrt(gate_chi2 * largest)
        area[rows] = np.pi * gate_chi2 * np.sqrt(det)
    return Windows(px, inv_cov, radius, area, visible)


def pixel_sigmas(uncertainty: PointUncertainty, world_from_cam: Array, points_world: Array,
                 camera: Camera, keypoint_sigma_px: float) -> Array:
    """(L,) isotropic pixel noise of each projection besides the prior's: the keypoint's
    localisation and the landmark's depth uncertainty seen from the prior, in quadrature."""
    with np.errstate(invalid="ignore", divide="ignore"):
        depth_px = uncertainty.pixel_sigmas(world_from_cam, points_world, camera)
    depth_px = np.where(np.isfinite(depth_px), depth_px, 0.0)
    return np.sqrt(keypoint_sigma_px**2 + depth_px**2)


def match_in_windows(feats: Features, windows: Windows, rows: IntArray,
                     map_desc: npt.NDArray[Any], gate_chi2: float, *, ratio: float,
                     background_quantile: float, background: float | None = None
                     ) -> tuple[IntArray, IntArray]:
    """Matches of the landmarks ``rows`` (their windows, descriptors ``map_desc[rows]``) to
    query keypoints inside their gates: (M,) query keypoint indices and (M,) landmark rows,
    one to one. Every keypoint inside a landmark's gate is a candidate
    (:func:`.prior_match.gated_best`); the best descriptor must beat the second by
    ``ratio`` and be closer than the ``background_quantile`` of unrelated descriptor pairs
    (as guided matching's; ``background``: that distance, where the caller has it for these
    descriptors already)."""
    empty = np.zeros(0, np.int64)
    if len(feats) < 2 or len(rows) == 0:
        return empty, empty
    best, second, index = gated_best(feats.keypoints_px, feats.descriptors, windows.px[rows],
                                     windows.inv_cov[rows], windows.radius_px[rows],
                                     map_desc[rows], gate_chi2)
    limit = (background if background is not None
             else background_distance(feats.descriptors, map_desc, background_quantile))
    ok = np.isfinite(best) & (best < ratio * second) & (best < limit)
    return _one_to_one(index[ok], rows[ok].astype(np.int64), best[ok])


def search_around(feats: Features, camera: Camera, world_from_cam: Array,
                  map_desc: npt.NDArray[Any], points_world: Array, radius_px: float, *,
                  ratio: float, background_quantile: float, background: float | None = None
                  ) -> tuple[IntArray, IntArray]:
    """Guided matching around a solved pose: the landmarks (descriptors (L, D), points
    (L, 3)) visible from ``world_from_cam`` matched to the query keypoints within
    ``radius_px`` of their projection, with :func:`match_in_windows`'s tests (a circular
    window is the gate of an isotropic covariance ``radius_px^2 I`` at chi-square 1).
    (M,) query keypoint indices and (M,) landmark rows, one to one."""
    px, visible = project_into(camera, world_from_cam, points_world)
    n = len(points_world)
    inv_cov = np.zeros((n, 2, 2))
    inv_cov[:, 0, 0] = inv_cov[:, 1, 1] = 1.0 / radius_px**2
    radius = np.where(visible, radius_px, np.inf)
    windows = Windows(px, inv_cov, radius, np.where(visible, np.pi * radius_px**2, np.inf),
                      visible)
    return match_in_windows(feats, windows, np.flatnonzero(visible), map_desc, 1.0,
                            ratio=ratio, background_quantile=background_quantile,
                            background=background)


def window_chance(inlier_threshold_px: float | None, areas_px: Array) -> float:
    """The probability that a wrong match agrees with a pose (inlier threshold
    ``inlier_threshold_px``) by chance when each match was drawn from its window (areas
    ``areas_px``) rather than from the whole image: ``pi t^2 / area`` (at most 1) averaged
    over the matches. The binomial with this mean bounds the tail of the matches'
    Poisson-binomial count beyond its mean (Hoeffding 1956), which is what the false-alarm
    test reads."""
    t = inlier_threshold_px
    if t is None or len(areas_px) == 0:
        return 0.0
    return float(np.mean(np.minimum(np.pi * t * t / np.maximum(areas_px, 1e-12), 1.0)))
