"""PTAM's relocaliser (thesis 3.1.2): ESM alignment of blurred thumbnails in SE(2), then the
camera rotation (SO(3), about the keyframe's centre) that moves two image points as that SE(2)
motion does.

Alignment. The keyframe's thumbnail is the template T, the query's the input I. A warp W
(SE(2), rotation alpha about the thumbnail centre and translation t, thumbnail pixels) maps a
template pixel x to the input pixel W(x) that shows the same scene point; ESM (Benhimane and
Malis 2004) minimises ``sum_x [I(W(x)) - T(x)]^2`` (3.1) by Gauss-Newton with compositional
updates ``W <- W exp(dp)``, the Jacobian at dp = 0 built from the average of the template's and
the warped input's gradients (3.10-3.12: ``[-y g_x + x g_y, g_x, g_y]``, x and y centred), and
``dp`` from the 3x3 normal equations (3.8, 3.9). The residual's mean is removed at every
iteration, which absorbs a brightness offset between the two images. Levels go coarse to fine
(each half the size of the next), the translation doubling from one level to the next.

Rotation. Two template points ``u = c +- (d, 0)`` around the principal point c are unprojected
with the keyframe camera; Gauss-Newton finds the rotation R (``query_from_kf``) for which the
query camera projects them onto ``W(u)`` (3.13-3.16, numerical Jacobian so any camera model
works). The query's ``world_from_cam`` is then ``world_from_kf @ [R^T | 0]``: the keyframe
camera turned about its own centre, as in PTAM.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, ClassVar

import cv2
import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.errors import ConfigError, MapError
from ...core.frame import Frame, Keyframe
from ...core.geometry import so3_exp
from ...core.map import MapState
from ...core.numeric import zncc
from ..place.base import PlaceCandidate
from .base import PoseEstimate, PoseFinder, register

Array = npt.NDArray[np.float64]
Image = npt.NDArray[np.floating[Any]]


# -- SE(2) warps -------------------------------------------------------------------------------
def se2(alpha: float, tx: float, ty: float) -> Array:
    """(3, 3) warp ``x -> R(alpha) x + t`` with ``R = [[cos, -sin], [sin, cos]]`` (the
    rotation whose Jacobian is thesis eq. 3.6; eq. 3.2 prints the transposed matrix)."""
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


def se2_params(warp: Array) -> tuple[float, float, float]:
    """(alpha, tx, ty) of an SE(2) warp matrix."""
    return float(np.arctan2(warp[1, 0], warp[0, 0])), float(warp[0, 2]), float(warp[1, 2])


def about_centre(warp_centred: Array, size: tuple[int, int]) -> Array:
    """The warp in absolute pixels of an image of ``size`` (w, h), given in pixels relative to
    the image centre ``((w - 1) / 2, (h - 1) / 2)``."""
    w, h = size
    shift = np.array([[1.0, 0.0, (w - 1) / 2], [0.0, 1.0, (h - 1) / 2], [0.0, 0.0, 1.0]])
    return shift @ warp_centred @ np.linalg.inv(shift)


def rescale_centred(warp_centred: Array, factor: float) -> Array:
    """The same motion for an image scaled by ``factor`` (centred coordinates scale exactly)."""
    out = warp_centred.copy()
    out[:2, 2] *= factor
    return out


def warp_image(image: Image, warp_centred: Array) -> tuple[Image, npt.NDArray[np.bool_]]:
    """``I(W(x))`` on the grid of ``image`` (bilinear) and the (H, W) mask of pixels whose
    source and both neighbours' sources lie inside ``image``."""
    h, w = image.shape
    absolute = about_centre(warp_centred, (w, h))
    warped = np.asarray(cv2.warpAffine(image, absolute[:2], (w, h),
                                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                       borderMode=cv2.BORDER_REPLICATE), dtype=np.float32)
    ys, xs = np.mgrid[0:h, 0:w]
    src_x = absolute[0, 0] * xs + absolute[0, 1] * ys + absolute[0, 2]
    src_y = absolute[1, 0] * xs + absolute[1, 1] * ys + absolute[1, 2]
    # One pixel of margin: the warped image's central-difference gradient must not see the border.
    mask = (src_x >= 1) & (src_x <= w - 2) & (src_y >= 1) & (src_y <= h - 2)
    mask[[0, -1], :] = False
    mask[:, [0, -1]] = False
    return warped, mask


# -- ESM alignment -----------------------------------------------------------------------------
@dataclass(frozen=True)
class Se2Alignment:
    """Result of :func:`align_se2`: ``warp_centred`` (3, 3) maps centred template pixels of the
    finest level to centred input pixels; NCC of the aligned thumbnails before and after."""

    warp_centred: Array
    size: tuple[int, int]
    ncc: float
    ncc_initial: float
    overlap: float
    iterations: int
    converged: bool

    @property
    def warp_px(self) -> Array:
        """(3, 3) warp in absolute pixels of the finest thumbnail."""
        return about_centre(self.warp_centred, self.size)


def _esm_step(template: Image, grad_t: tuple[Image, Image], image: Image, warp_centred: Array,
              grid: tuple[Image, Image]) -> Array | None:
    """One ESM Gauss-Newton increment (alpha, tx, ty) (3.8-3.12); None if degenerate."""
    warped, mask = warp_image(image, warp_centred)
    if mask.sum() < 10:
        return None
    gy_w, gx_w = np.gradient(warped)
    gx = 0.5 * (grad_t[1] + gx_w)[mask]  # ESM: mean of template and warped-input gradients
    gy = 0.5 * (grad_t[0] + gy_w)[mask]
    xs, ys = grid[0][mask], grid[1][mask]
    jac = np.column_stack([-ys * gx + xs * gy, gx, gy]).astype(np.float64)
    residual = (warped - template)[mask].astype(np.float64)
    residual -= residual.mean()  # brightness offset between the two thumbnails
    hessian = jac.T @ jac
    if np.linalg.cond(hessian) > 1e12:
        return None
    return np.asarray(-np.linalg.solve(hessian, jac.T @ residual), dtype=np.float64)


def esm_level(template: Image, image: Image, warp_centred: Array, *, max_iterations: int,
              convergence_px: float) -> tuple[Array, int, bool]:
    """Refine ``warp_centred`` on one level: (warp, iterations, converged). Converged means the
    last increment moved no template corner by more than ``convergence_px``."""
    h, w = template.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    grid = (xs - (w - 1) / 2, ys - (h - 1) / 2)
    gy_t, gx_t = (np.asarray(g, np.float32) for g in np.gradient(template))
    radius = 0.5 * np.hypot(w, h)
    for it in range(1, max_iterations + 1):
        step = _esm_step(template, (gy_t, gx_t), image, warp_centred, grid)
        if step is None or not np.all(np.isfinite(step)):
            return warp_centred, it, False
        warp_centred = warp_centred @ se2(*step)
        if abs(step[0]) * radius + np.hypot(step[1], step[2]) < convergence_px:
            return warp_centred, it, True
    return warp_centred, max_iterations, False


def align_se2(templates: list[Image], images: list[Image], *, max_iterations: int = 30,
              convergence_px: float = 0.01, init_centred: Array | None = None) -> Se2Alignment:
    """Align thumbnail pyramids (coarse to fine, each level twice the size of the previous):
    the input ``images`` onto the ``templates``; ``init_centred`` is a warp at the coarsest
    level (default identity)."""
    warp = np.eye(3) if init_centred is None else np.asarray(init_centred, np.float64)
    total, converged = 0, False
    for level, (tpl, img) in enumerate(zip(templates, images, strict=True)):
        if level:
            warp = rescale_centred(warp, tpl.shape[1] / templates[level - 1].shape[1])
        warp, its, converged = esm_level(tpl, img, warp, max_iterations=max_iterations,
                                         convergence_px=convergence_px)
        total += its
    finest_t, finest_i = templates[-1], images[-1]
    identity_warped, identity_mask = warp_image(finest_i, np.eye(3))
    warped, mask = warp_image(finest_i, warp)
    # Candidates are ranked by this NCC (find_pose keeps the best): a flat thumbnail scores -1,
    # below any real alignment.
    return Se2Alignment(warp, (finest_t.shape[1], finest_t.shape[0]),
                        zncc(finest_t, warped, mask, flat=-1.0),
                        zncc(finest_t, identity_warped, identity_mask, flat=-1.0),
                        float(mask.mean()), total,
                        converged)


# -- SE(2) -> SO(3) ----------------------------------------------------------------------------
def thumb_to_full(px_thumb: Array, thumb_size: tuple[int, int], camera: Camera) -> Array:
    """(N, 2) thumbnail pixels to full-resolution pixels of ``camera`` (pixel centres at
    integers in both, as :meth:`Camera.scaled`)."""
    scale = np.array([camera.width / thumb_size[0], camera.height / thumb_size[1]])
    return (np.asarray(px_thumb, np.float64) + 0.5) * scale - 0.5


def full_to_thumb(px_full: Array, thumb_size: tuple[int, int], camera: Camera) -> Array:
    """Inverse of :func:`thumb_to_full`."""
    scale = np.array([thumb_size[0] / camera.width, thumb_size[1] / camera.height])
    return (np.asarray(px_full, np.float64) + 0.5) * scale - 0.5


def rotation_from_se2(warp_px: Array, thumb_size: tuple[int, int], camera_kf: Camera,
                      camera_query: Camera, *, offset_px: float, iterations: int = 10
                      ) -> Array | None:
    """(3, 3) rotation ``query_from_kf`` whose image motion matches the thumbnail warp
    ``warp_px`` (3, 3, keyframe thumbnail -> query thumbnail) at the two points
    ``principal point +- (offset_px, 0)`` (thumbnail pixels), Gauss-Newton on 3.13-3.16 with
    the cameras' own models; None if a point leaves the image plane."""
    centre = full_to_thumb(np.array([[camera_kf.cx, camera_kf.cy]]), thumb_size, camera_kf)[0]
    u_thumb = centre + np.array([[offset_px, 0.0], [-offset_px, 0.0]])
    targets_thumb = u_thumb @ warp_px[:2, :2].T + warp_px[:2, 2]
    bearings_kf = camera_kf.unproject(thumb_to_full(u_thumb, thumb_size, camera_kf))
    targets = thumb_to_full(targets_thumb, thumb_size, camera_query).ravel()
    query_from_kf = np.eye(3)
    for _ in range(iterations):
        residual = targets - camera_query.project(bearings_kf @ query_from_kf.T).ravel()
        jac = _rotation_jacobian(bearings_kf, query_from_kf, camera_query)
        if not (np.all(np.isfinite(residual)) and np.all(np.isfinite(jac))):
            return None
        step = np.linalg.lstsq(jac, residual, rcond=None)[0]
        query_from_kf = so3_exp(step) @ query_from_kf  # left perturbation, as PTAM
        if np.linalg.norm(step) < 1e-9:  # radians; converges in a few iterations
            break
    return query_from_kf


def _rotation_jacobian(bearings: Array, rotation: Array, camera: Camera, eps: float = 1e-6
                       ) -> Array:
    """(2N, 3) derivative of the projections of ``rotation @ bearings`` under a left
    perturbation ``exp(xi) @ rotation`` (central differences: works for every camera model)."""
    cols = []
    for axis in np.eye(3):
        plus = camera.project(bearings @ (so3_exp(eps * axis) @ rotation).T).ravel()
        minus = camera.project(bearings @ (so3_exp(-eps * axis) @ rotation).T).ravel()
        cols.append((plus - minus) / (2 * eps))
    return np.column_stack(cols)


def pose_from_rotation(world_from_kf: Array, query_from_kf: Array) -> Array:
    """``world_from_cam`` of the query: the keyframe camera turned about its centre,
    ``world_from_kf @ [query_from_kf^T | 0]``."""
    kf_from_query = np.eye(4)
    kf_from_query[:3, :3] = query_from_kf.T
    return world_from_kf @ kf_from_query


# -- the pose finder ---------------------------------------------------------------------------
@register("esm")
class EsmPoseFinder(PoseFinder):
    """PTAM relocaliser: SE(2) ESM alignment of thumbnails, then a rotation about the
    keyframe's centre (thesis 3.1.2); evidence is the NCC of the aligned thumbnails."""

    needs_agreement: ClassVar[bool] = True
    #: Its keyframe thumbnails (80x60 and 40x30) are made from the pixels when first aligned.
    reads_keyframe_images: ClassVar[bool] = True

    @dataclass(frozen=True)
    class Conf:
        #: Finest thumbnail size; each of the ``levels`` coarser ones is half the previous.
        width: int = 80
        height: int = 60
        levels: int = 2
        #: Gaussian blur of every level, in that level's pixels (PTAM: 2.5 at 40x30).
        blur_sigma: float = 2.5
        max_iterations: int = 30
        #: Stop a level when an increment moves no thumbnail corner by more than this (px).
        convergence_px: float = 0.01
        #: Candidates aligned (best first); the one with the highest NCC wins.
        candidates: int = 1
        #: Fit points +- this fraction of the thumbnail width around the principal point
        #: (PTAM: +-5 px on its 40-px-wide image).
        fit_offset: float = 0.125
        #: Fewer template pixels than this fraction landing inside the query: no estimate.
        min_overlap: float = 0.3

        def __post_init__(self) -> None:
            coarsest = min(self.width, self.height) >> (self.levels - 1) if self.levels >= 1 else 0
            if self.levels < 1 or coarsest < 8:
                raise ConfigError(f"esm: levels must be >= 1 and leave the coarsest thumbnail at "
                                  f"least 8 px; got {self.width}x{self.height} with {self.levels}")
            if self.blur_sigma <= 0 or self.max_iterations < 1 or self.convergence_px <= 0:
                raise ConfigError("esm: blur_sigma, max_iterations and convergence_px must be "
                                  "positive")
            if (self.candidates < 1 or not 0 < self.fit_offset < 0.5
                    or not 0 <= self.min_overlap <= 1):
                raise ConfigError("esm: expected candidates >= 1, 0 < fit_offset < 0.5, "
                                  "0 <= min_overlap <= 1")

    def __init__(self, conf: EsmPoseFinder.Conf) -> None:
        super().__init__(conf)
        self.conf: EsmPoseFinder.Conf = conf

    def thumbnails(self, frame: Frame) -> list[Image]:
        """The frame's blurred zero-mean thumbnails, coarsest first (cached in the frame)."""
        c = self.conf
        return [frame.small_blurry_image(c.width >> lvl, c.height >> lvl, c.blur_sigma)
                for lvl in reversed(range(c.levels))]

    def align(self, query: Frame, keyframe: Keyframe) -> Se2Alignment:
        """SE(2) alignment of the query's thumbnails onto the keyframe's."""
        return align_se2(self.thumbnails(keyframe), self.thumbnails(query),
                         max_iterations=self.conf.max_iterations,
                         convergence_px=self.conf.convergence_px)

    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        """Align against each of the first ``candidates`` keyframes; keep the best NCC."""
        best: tuple[float, PoseEstimate] | None = None
        for cand in candidates[:self.conf.candidates]:
            try:
                keyframe = state.keyframe(cand.keyframe_id)
            except MapError:
                continue  # removed since the place finder ranked it
            estimate = self._estimate(query, keyframe)
            if estimate is not None and estimate.ncc is not None and (
                    best is None or estimate.ncc > best[0]):
                best = (estimate.ncc, estimate)
        return None if best is None else best[1]

    def _estimate(self, query: Frame, keyframe: Keyframe) -> PoseEstimate | None:
        t0 = time.perf_counter()
        alignment = self.align(query, keyframe)
        t1 = time.perf_counter()
        if alignment.overlap < self.conf.min_overlap:
            return None
        query_from_kf = rotation_from_se2(alignment.warp_px, alignment.size, keyframe.camera,
                                          query.camera,
                                          offset_px=self.conf.fit_offset * self.conf.width)
        if query_from_kf is None:
            return None
        world_from_cam = pose_from_rotation(keyframe.world_from_cam, query_from_kf)
        timings: dict[str, Any] = {"align": t1 - t0, "solve": time.perf_counter() - t1}
        return PoseEstimate(world_from_cam=world_from_cam, keyframe_ids=[keyframe.id],
                            ncc=alignment.ncc, timings=timings)
