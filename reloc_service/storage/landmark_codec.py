"""Landmark geometry on disk (snapshot format 4): float32 where the rounding is far below
what each landmark's own uncertainty allows, float64 otherwise.

A landmark's point is stored as the float32 offset (world axes, metres) from the centre of
the keyframe of its first observation, its *anchor*. Anchored, float32's relative precision
(2**-24) applies to the landmark's range from a camera that saw it, not to its distance from
the world origin: a point 300 m from the origin and 2 m from its camera is kept to about
0.1 micrometre, where the same point in world float32 would move by up to 15.

A snapshot keeps that form only when, for every landmark, the rounding error is below
:data:`ROUNDING_SHARE` of the landmark's 1-sigma position uncertainty (:func:`position_sigmas`:
its triangulated depth sigma, at least the pixel localisation floor P3P uses); otherwise
the map keeps float64 points and sigmas (format 3's columns), so no map loses more.

On request (``StoredParts.landmark_points == "float16"``, format 10) the offsets are stored
float16 when every landmark's rounding error is at most :data:`HALF_ROUNDING_SHARE` of its
1-sigma uncertainty; otherwise the float32 test above applies.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.frame import Keyframe
from ..core.landmark_table import LandmarkColumns
from ..core.triangulation import TriangulationConf

Array = npt.NDArray[np.float64]

#: Largest rounding error accepted, as a share of a landmark's 1-sigma position uncertainty.
#: An independent error ``e`` adds in quadrature: ``sqrt(s^2 + e^2) <= s (1 + share^2 / 2)``,
#: so at 1/100 every uncertainty (P3P's residual weights, verification's sigma-scaled
#: thresholds) grows by at most 0.005 %, and a point's projection moves by at most 1/100 of
#: the keypoint localisation sigma (0.005 px) from the floor's camera: far below what any
#: decision on a 0.5 px keypoint can resolve.
ROUNDING_SHARE = 0.01
#: Largest rounding error of float16 offsets, as a share of the landmark's 1-sigma position
#: uncertainty. float16 rounds an offset to within 2**-11 of its length (11-bit significand),
#: that is 0.45 of the uncertainty floor (a 0.5 px keypoint at the landmark's range) at a
#: 460 px focal length. At 1/2 every uncertainty grows by at most 12 % in quadrature, and a
#: 99 % chi-square gate on the landmark's reprojection (2 dof, 9.21) keeps a true match with
#: probability at least 98.4 % (noncentral chi-square, noncentrality 1/4) instead of 99 %.
#: A map with a landmark beyond it (a focal length above about 510 px with exact depth, where
#: only the pixel floor bounds the uncertainty) keeps float32.
HALF_ROUNDING_SHARE = 0.5
#: Keypoint localisation (1 sigma, pixels) of the uncertainty floor: the triangulation's
#: (and P3P's) default ``keypoint_sigma_px``.
KEYPOINT_SIGMA_PX = TriangulationConf.keypoint_sigma_px
#: Column (file) name of the anchored float32 points.
ANCHORED_POINTS = "anchored_points_world"


def anchors(columns: LandmarkColumns, keyframes: Mapping[int, Keyframe]
            ) -> tuple[Array, Array] | None:
    """(L, 3) world centre of each landmark's anchor keyframe (its first observation's) and
    (L,) that keyframe's focal length (pixels, the larger of fx, fy); None when a landmark
    has no observation or observes a keyframe not in ``keyframes``."""
    offsets = np.asarray(columns.obs_offsets, np.int64)
    if len(columns.ids) == 0 or np.any(np.diff(offsets) <= 0):
        return None
    first_kf = np.asarray(columns.obs_keyframe, np.int64)[offsets[:-1]]
    kf_ids = np.array(sorted(keyframes), np.int64)
    if len(kf_ids) == 0:
        return None
    pos = np.clip(np.searchsorted(kf_ids, first_kf), 0, len(kf_ids) - 1)
    if not np.array_equal(kf_ids[pos], first_kf):
        return None
    kfs = [keyframes[int(k)] for k in kf_ids]
    centres = np.array([kf.world_from_cam[:3, 3] for kf in kfs], np.float64).reshape(-1, 3)
    focal = np.array([max(kf.camera.fx, kf.camera.fy) for kf in kfs], np.float64)
    return centres[pos], focal[pos]


def position_sigmas(points_world: Array, centres_world: Array, focal_px: Array,
                    depth_sigmas_m: Array) -> Array:
    """(L,) 1-sigma position uncertainty of landmarks, metres: the depth sigma, at least a
    ``KEYPOINT_SIGMA_PX`` keypoint at the landmark's range from its anchor (the floor P3P's
    point sigmas use; it bounds landmarks whose sigma is unknown, 0: depth maps, clients)."""
    ranges = np.linalg.norm(points_world - centres_world, axis=1)
    return np.maximum(depth_sigmas_m, ranges * KEYPOINT_SIGMA_PX / focal_px)


def encode_geometry(columns: LandmarkColumns, keyframes: Mapping[int, Keyframe], *,
                    exact: bool = False, half: bool = False) -> dict[str, np.ndarray]:
    """The landmark geometry columns a snapshot stores: with ``half``, ``{ANCHORED_POINTS:
    (L, 3) float16, "depth_sigmas_m": (L,) float32}`` when every offset's rounding error is at
    most ``HALF_ROUNDING_SHARE`` of its :func:`position_sigmas`; else ``{ANCHORED_POINTS: (L,
    3) float32, "depth_sigmas_m": (L,) float32}`` when every landmark's rounding error (point
    and sigma) is at most ``ROUNDING_SHARE`` of it, else (or when ``exact``)
    ``{"points_world": (L, 3) float64, "depth_sigmas_m": (L,) float64}`` as held."""
    points = np.asarray(columns.points_world, np.float64)
    sigmas = np.asarray(columns.depth_sigmas_m, np.float64)
    full = {"points_world": points, "depth_sigmas_m": sigmas}
    found = None if exact else anchors(columns, keyframes)
    if found is None:
        return full
    centres, focal = found
    with np.errstate(over="ignore", invalid="ignore"):
        sigmas32 = sigmas.astype(np.float32)
        sigma_error = np.abs(sigmas32.astype(np.float64) - sigmas)
        uncertainty = position_sigmas(points, centres, focal, sigmas)
        sigma_fits = bool(np.all(sigma_error <= ROUNDING_SHARE * uncertainty))
        for dtype, share in ((np.float16, HALF_ROUNDING_SHARE),) * half + (
                (np.float32, ROUNDING_SHARE),):
            offsets = (points - centres).astype(dtype)
            point_error = np.linalg.norm(centres + offsets.astype(np.float64) - points, axis=1)
            # NaN or overflow compares False: such a map keeps float64
            if sigma_fits and bool(np.all(point_error <= share * uncertainty)):
                return {ANCHORED_POINTS: offsets, "depth_sigmas_m": sigmas32}
    return full


class RowDecoded:
    """A read-only float64 column decoded row by row from a narrower stored one: ``column[rows]``
    (an index, slice, index array or mask) decodes only those rows, so a loaded map keeps the
    memory-mapped file on disk until queries touch it, as format 3's float64 columns were;
    ``np.asarray(column)`` decodes every row."""

    dtype = np.dtype(np.float64)

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.shape = shape
        self.ndim = len(shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, rows: Any) -> Array:
        return self._rows(rows)

    def __array__(self, dtype: Any = None, copy: Any = None) -> Array:
        out = self._rows(slice(None))
        return out if dtype is None else out.astype(dtype)

    def _rows(self, rows: Any) -> Array:
        raise NotImplementedError


class WidenedColumn(RowDecoded):
    """A float32 column (depth sigmas) read as float64."""

    def __init__(self, column: np.ndarray) -> None:
        super().__init__(tuple(column.shape))
        self._column = column

    def _rows(self, rows: Any) -> Array:
        return np.asarray(self._column[rows], np.float64)


class AnchoredPoints(RowDecoded):
    """(L, 3) float64 world points: the centre of each landmark's anchor keyframe plus its
    stored float32 (or float16) offset (:func:`encode_geometry`), decoded per row."""

    def __init__(self, offsets: npt.NDArray[np.floating[Any]], anchor: np.ndarray,
                 centres_world: Array) -> None:
        super().__init__((len(offsets), 3))
        self._offsets, self._anchor, self._centres = offsets, anchor, centres_world

    def _rows(self, rows: Any) -> Array:
        return self._centres[self._anchor[rows]] + self._offsets[rows].astype(np.float64)


def anchored_points(anchored: npt.NDArray[np.floating[Any]], obs_offsets: npt.NDArray[np.int64],
                    obs_keyframe: npt.NDArray[np.int64], keyframes: Mapping[int, Keyframe]
                    ) -> AnchoredPoints:
    """The (L, 3) world points of :func:`encode_geometry`'s offsets ``anchored`` (kept as
    they are, memory-mapped), decoded on read; the observation columns already checked
    against ``keyframes``. ValueError when a landmark has no observation to anchor it."""
    offsets = np.asarray(obs_offsets, np.int64)
    kf_ids = np.array(sorted(keyframes), np.int64)
    centres = np.array([keyframes[int(k)].world_from_cam[:3, 3] for k in kf_ids],
                       np.float64).reshape(-1, 3)
    if len(anchored) == 0:
        return AnchoredPoints(anchored, np.zeros(0, np.int32), centres)
    if np.any(np.diff(offsets) <= 0):
        raise ValueError("anchored landmark points need an observation per landmark")
    first_kf = np.asarray(obs_keyframe, np.int64)[offsets[:-1]]
    # one small index per landmark (int16 up to 32767 keyframes) is all load makes
    anchor = np.searchsorted(kf_ids, first_kf).astype(
        np.int16 if len(kf_ids) <= np.iinfo(np.int16).max else np.int32)
    return AnchoredPoints(anchored, anchor, centres)


def decode_points(anchored: npt.NDArray[np.floating[Any]], obs_offsets: npt.NDArray[np.int64],
                  obs_keyframe: npt.NDArray[np.int64], keyframes: Mapping[int, Keyframe]
                  ) -> Array:
    """(L, 3) float64 world points of :func:`anchored_points`, every row decoded."""
    return np.asarray(anchored_points(anchored, obs_offsets, obs_keyframe, keyframes))
