"""Training samples for the ferns: random warps of whole images (thesis 3.2.2; Ozuysal et al.).

Each real view of a landmark (a keypoint of a keyframe) is multiplied by random warps: a
rotation, a scale, optionally a full affine (independent scales along a random direction),
white Gaussian noise and a Gaussian blur. A keyframe image is warped ONCE per random transform
(``cv2.warpAffine``), every keypoint position goes through the same affine, and the fern tests
of all keypoints are read from the warped image at once (no patch is cut, no Python loop per
patch).

Everything is a function of ``(seed, key, warp index)`` and of the keyframe image alone (never
of which keypoints are sampled together), so the samples of an observation can be regenerated
bit for bit later, to remove them from the counts.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ...core.errors import ConfigError
from .fern_tests import FernTests

Array = npt.NDArray[np.float64]

#: Side of the fixed noise texture the per-warp noise is cut from (float32, 16 MB).
_NOISE_SIDE = 2048


@dataclass(frozen=True)
class WarpConf:
    """Random warps per real view (Ozuysal's training; the thesis kept rotation and scale).

    ``num_warps`` samples per view, the first the real view itself if ``include_identity``.
    Rotation uniform in +-``max_rotation_rad``; scales uniform in [``min_scale``,
    ``max_scale``], drawn independently along a random direction when ``affine``; noise
    standard deviation uniform in [0, ``max_noise_sigma``] grey levels; extra blur uniform in
    [0, ``max_blur_sigma``] px. Every image (training and query) is smoothed by
    ``smoothing_sigma`` px before the tests."""

    num_warps: int = 100
    include_identity: bool = True
    max_rotation_rad: float = math.pi
    min_scale: float = 0.6
    max_scale: float = 1.5
    affine: bool = True
    max_noise_sigma: float = 5.0
    max_blur_sigma: float = 1.0
    smoothing_sigma: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.num_warps < 1:
            raise ConfigError(f"num_warps must be >= 1, got {self.num_warps}")
        if not 0 < self.min_scale <= self.max_scale:
            raise ConfigError(f"expected 0 < min_scale <= max_scale, got {self.min_scale}, "
                              f"{self.max_scale}")
        if min(self.max_rotation_rad, self.max_noise_sigma, self.max_blur_sigma,
               self.smoothing_sigma) < 0:
            raise ConfigError("max_rotation_rad, max_noise_sigma, max_blur_sigma and "
                              "smoothing_sigma must be >= 0")


@dataclass(frozen=True)
class Warps:
    """W random warps: (W, 2, 2) linear parts, (W,) noise sigma and extra blur sigma, (W, 2)
    int64 offsets into the noise texture."""

    linear: Array
    noise_sigma: Array
    blur_sigma: Array
    noise_offset: npt.NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.linear)

    def take(self, indices: npt.ArrayLike) -> Warps:
        """The warps ``indices`` (each keeps its parameters: samples do not change)."""
        idx = np.asarray(indices, dtype=np.int64)
        return Warps(self.linear[idx], self.noise_sigma[idx], self.blur_sigma[idx],
                     self.noise_offset[idx])


def draw_warps(conf: WarpConf, key: int) -> Warps:
    """The ``conf.num_warps`` warps of image ``key`` (a keyframe id), seeded by
    ``(conf.seed, key)``: the same key always gets the same warps."""
    rng = np.random.default_rng([conf.seed, int(key)])
    n = conf.num_warps
    theta = rng.uniform(-conf.max_rotation_rad, conf.max_rotation_rad, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    scales = rng.uniform(conf.min_scale, conf.max_scale, (n, 2))
    if not conf.affine:
        scales[:, 1] = scales[:, 0]
    # Ozuysal et al.: A = R_theta R_phi^-1 diag(l1, l2) R_phi.
    linear = _rot(theta) @ np.swapaxes(_rot(phi), 1, 2) @ _diag(scales) @ _rot(phi)
    noise = rng.uniform(0.0, conf.max_noise_sigma, n)
    blur = rng.uniform(0.0, conf.max_blur_sigma, n)
    offset = rng.integers(0, _NOISE_SIDE, (n, 2))
    if conf.include_identity:
        linear[0], noise[0], blur[0] = np.eye(2), 0.0, 0.0
    return Warps(linear, noise, blur, offset)


def _rot(angle: Array) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _diag(scales: Array) -> Array:
    out = np.zeros((len(scales), 2, 2))
    out[:, 0, 0], out[:, 1, 1] = scales[:, 0], scales[:, 1]
    return out


def prepare_image(image: npt.NDArray[np.uint8], smoothing_sigma: float) -> npt.NDArray[np.float32]:
    """A query image as the tests see it: float32, Gaussian-smoothed by ``smoothing_sigma``."""
    img = image.astype(np.float32)
    if smoothing_sigma <= 0:
        return img
    return np.asarray(cv2.GaussianBlur(img, (0, 0), smoothing_sigma), np.float32)


@functools.cache
def _noise_texture() -> npt.NDArray[np.float32]:
    """A fixed (2048, 2048) float32 N(0, 1) texture; per-warp noise is a window of it."""
    return np.random.default_rng(0x5EED).standard_normal((_NOISE_SIDE, _NOISE_SIDE), np.float32)


def _noise_window(height: int, width: int, offset: npt.NDArray[np.int64]
                  ) -> npt.NDArray[np.float32]:
    """(height, width) window of the noise texture at ``offset`` (y, x) (reduced so that the
    window fits, a zero-copy view; wrapping around only for canvases over 2048 px)."""
    tex = _noise_texture()
    if height <= _NOISE_SIDE and width <= _NOISE_SIDE:
        oy = int(offset[0]) % (_NOISE_SIDE - height + 1)
        ox = int(offset[1]) % (_NOISE_SIDE - width + 1)
        return tex[oy:oy + height, ox:ox + width]
    oy, ox = int(offset[0]), int(offset[1])
    rows = (oy + np.arange(height)) % _NOISE_SIDE
    cols = (ox + np.arange(width)) % _NOISE_SIDE
    return tex[rows[:, None], cols[None, :]]


def padding_for(conf: WarpConf, patch_size: int) -> int:
    """Reflected border added around an image before warping, so patches of keypoints near
    the border see image-like content after any warp (half a patch diagonal, unscaled)."""
    return int(math.ceil(patch_size * 0.75 / conf.min_scale)) + 4


def pad_image(image: npt.NDArray[np.uint8], pad: int) -> npt.NDArray[np.float32]:
    """(H + 2 pad, W + 2 pad) float32 copy of ``image`` with a reflected border."""
    return cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_REFLECT_101).astype(np.float32)


def warp_affine(linear: Array, image_size: tuple[int, int], pad: int
                ) -> tuple[Array, tuple[int, int]]:
    """The (2, 3) affine from image pixels to the canvas of one warp, and the canvas (width,
    height): ``linear`` about the image centre, translated so the warped padded image fits."""
    w, h = image_size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    corners = np.array([[-pad, -pad], [w - 1 + pad, -pad], [-pad, h - 1 + pad],
                        [w - 1 + pad, h - 1 + pad]], np.float64)
    warped = (corners - centre) @ linear.T + centre
    # An integer shift keeps the identity warp on the pixel grid (no half-pixel resampling).
    lo = np.floor(warped.min(0))
    size = np.ceil(warped.max(0) - lo).astype(int) + 1
    affine = np.column_stack([linear, centre - linear @ centre - lo])
    return affine, (int(size[0]), int(size[1]))


def warp_image(padded: npt.NDArray[np.float32], image_size: tuple[int, int], pad: int,
               warps: Warps, index: int, conf: WarpConf) -> tuple[npt.NDArray[np.float32], Array]:
    """Warp ``index`` of a padded image: warped, noised, blurred and smoothed canvas (float32)
    and the (2, 3) affine from original image pixels to canvas pixels."""
    affine, size = warp_affine(warps.linear[index], image_size, pad)
    from_padded = affine.copy()
    from_padded[:, 2] -= affine[:, :2] @ np.array([pad, pad], np.float64)
    canvas = cv2.warpAffine(padded, from_padded, size, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT)
    if warps.noise_sigma[index] > 0:
        noise = _noise_window(size[1], size[0], warps.noise_offset[index])
        canvas = cv2.scaleAdd(noise, float(warps.noise_sigma[index]), canvas)
    sigma = math.hypot(conf.smoothing_sigma, float(warps.blur_sigma[index]))
    if sigma > 0:
        canvas = cv2.GaussianBlur(canvas, (0, 0), sigma)
    return np.asarray(canvas, np.float32), affine


def sample_leaves(classifier: FernTests, image: npt.NDArray[np.uint8],
                  points_px: npt.ArrayLike, warps: Warps, conf: WarpConf
                  ) -> npt.NDArray[np.uint16]:
    """Leaves of the patches at ``points_px`` (N, 2) of ``image`` under every warp:
    (W, N, M) uint16. One ``cv2.warpAffine`` per warp whatever N."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    out = np.zeros((len(warps), len(pts), classifier.num_ferns), np.uint16)
    if len(pts) == 0:
        return out
    pad = padding_for(conf, classifier.conf.patch_size)
    padded = pad_image(image, pad)
    size = (image.shape[1], image.shape[0])
    for w in range(len(warps)):  # one iteration per warp of the whole image
        canvas, affine = warp_image(padded, size, pad, warps, w, conf)
        out[w] = classifier.leaves_at(canvas, pts @ affine[:, :2].T + affine[:, 2])
    return out


def extract_patches(image: npt.ArrayLike, points_px: npt.ArrayLike, size: int
                    ) -> npt.NDArray[np.generic]:
    """(N, size, size) patches of ``image`` (H, W) centred (at ``size // 2``) on the rounded
    ``points_px`` (N, 2), border reflected; one fancy index of a sliding-window view."""
    img = np.asarray(image)
    pts = np.rint(np.asarray(points_px, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
    half = size // 2
    padded = np.pad(img, ((half, size - half), (half, size - half)), mode="reflect")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (size, size))
    # Window (y, x) of the padded image is centred on pixel (y, x) of the image.
    ys = np.clip(pts[:, 1], 0, img.shape[0] - 1)
    xs = np.clip(pts[:, 0], 0, img.shape[1] - 1)
    return windows[ys, xs]
