"""A fern's binary tests (thesis eq. 3.17): ``S`` pixel comparisons on a patch whose bits form
a leaf index in ``[0, 2^S)``; :class:`FernConf` (the classifier's shape) and
:class:`FernTests` (the drawn comparisons, and the leaves of patches or of image points)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...core.errors import ConfigError
from . import kernels

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
Leaves = npt.NDArray[np.uint16]

#: Leaves are stored as uint16, so a fern has at most 16 tests (65536 leaves).
MAX_TESTS = 16

@dataclass(frozen=True)
class FernConf:
    """Shape of a fern classifier: ``num_ferns`` (M) ferns of ``num_tests`` (S) pixel
    comparisons inside a ``patch_size`` square patch; ``regularization`` is Nr (eq. 3.23);
    ``seed`` draws the test pixel pairs."""

    num_ferns: int = 100
    num_tests: int = 12
    patch_size: int = 32
    regularization: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.num_ferns < 1:
            raise ConfigError(f"num_ferns must be >= 1, got {self.num_ferns}")
        if not 1 <= self.num_tests <= MAX_TESTS:
            raise ConfigError(f"num_tests must be in [1, {MAX_TESTS}], got {self.num_tests}")
        if self.patch_size < 4:
            raise ConfigError(f"patch_size must be >= 4, got {self.patch_size}")
        if not self.regularization > 0:
            raise ConfigError(f"regularization must be > 0, got {self.regularization}")


def draw_tests(conf: FernConf) -> tuple[IntArray, IntArray]:
    """Pixel pairs of every test: two (S * M, 2) int64 (dy, dx) offsets from the patch centre
    (``patch_size // 2``); test ``j`` of fern ``m`` is row ``j * M + m``; a pair's pixels differ."""
    rng = np.random.default_rng(conf.seed)
    p, n = conf.patch_size, conf.num_tests * conf.num_ferns
    first = rng.integers(0, p * p, n)
    second = (first + rng.integers(1, p * p, n)) % (p * p)  # uniform among the other pixels
    centre = p // 2

    def offsets(flat: IntArray) -> IntArray:
        return np.column_stack([flat // p - centre, flat % p - centre]).astype(np.int64)

    return offsets(first), offsets(second)


class FernTests:
    """The pixel tests of M ferns of S tests: patches or image positions -> leaves."""

    def __init__(self, conf: FernConf, off_a: IntArray | None = None,
                 off_b: IntArray | None = None) -> None:
        self.conf = conf
        if off_a is None or off_b is None:
            off_a, off_b = draw_tests(conf)
        self.off_a, self.off_b = off_a, off_b

    @property
    def num_ferns(self) -> int:
        return self.conf.num_ferns

    @property
    def num_tests(self) -> int:
        return self.conf.num_tests

    @property
    def num_leaves(self) -> int:
        """K = 2^S leaves per fern."""
        return 1 << self.conf.num_tests

    @property
    def num_rows(self) -> int:
        """M K rows of the model (fern, leaf)."""
        return self.num_ferns * self.num_leaves

    def leaves_from_patches(self, patches: npt.ArrayLike) -> Leaves:
        """(N, P, P) patches (any real dtype, centre at ``P // 2``) -> (N, M) uint16 leaves."""
        pat = np.asarray(patches)
        p = self.conf.patch_size
        if pat.ndim != 3 or pat.shape[1:] != (p, p):
            raise ValueError(f"patches: expected (N, {p}, {p}), got {pat.shape}")
        flat = pat.reshape(len(pat), p * p)
        c = p // 2
        ia = (self.off_a[:, 0] + c) * p + self.off_a[:, 1] + c
        ib = (self.off_b[:, 0] + c) * p + self.off_b[:, 1] + c
        return self._pack(flat[:, ia] < flat[:, ib])

    def leaves_at(self, image: npt.ArrayLike, points_px: npt.ArrayLike) -> Leaves:
        """Leaves of the patches of ``image`` (H, W) centred at ``points_px`` (N, 2) (x, y,
        rounded to the nearest pixel, clamped into the image) -> (N, M) uint16. Pixels
        outside the image repeat the border. Only the 2 S M test pixels are read: by one
        compiled pass with numba (:mod:`.kernels`), else by numpy gathers (the same leaves)."""
        img = np.asarray(image)
        if img.ndim != 2:
            raise ValueError(f"image: expected (H, W), got {img.shape}")
        pts = np.rint(np.asarray(points_px, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
        h, w = img.shape
        xs, ys = np.clip(pts[:, 0], 0, w - 1), np.clip(pts[:, 1], 0, h - 1)
        return self._leaves_at(img, xs, ys, compiled=kernels.compiled_leaves_at() is not None)

    def _leaves_at(self, img: npt.NDArray[Any], xs: IntArray, ys: IntArray, *,
                   compiled: bool) -> Leaves:
        """:meth:`leaves_at` of pixels ``(xs, ys)`` inside ``img``: compiled (numba), or by
        numpy's (N, S M) gathers from a copy padded only when a patch sticks out."""
        if compiled:
            leaves = np.empty((len(xs), self.num_ferns), np.uint16)
            kernel = kernels.compiled_leaves_at()
            assert kernel is not None  # leaves_at asks for this only when numba is there
            kernel(np.ascontiguousarray(img), xs, ys, self.off_a, self.off_b, self.num_ferns,
                   leaves)
            return leaves
        h, w = img.shape
        reach = self.conf.patch_size // 2 + 1
        inside = len(xs) == 0 or (xs.min() >= reach and ys.min() >= reach
                                   and xs.max() < w - reach and ys.max() < h - reach)
        pad = 0 if inside else reach  # pad (replicating the border) only when a patch sticks out
        if pad:
            img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
        stride = w + 2 * pad
        base = ((ys + pad) * stride + xs + pad)[:, None]
        flat = np.ascontiguousarray(img).ravel()
        lin_a = self.off_a[:, 0] * stride + self.off_a[:, 1]
        lin_b = self.off_b[:, 0] * stride + self.off_b[:, 1]
        return self._pack(flat[base + lin_a[None, :]] < flat[base + lin_b[None, :]])

    def _pack(self, bits: npt.NDArray[np.bool_]) -> Leaves:
        """(N, S * M) test outcomes (row j * M + m) -> (N, M) leaves, first test = top bit
        (thesis listing 3.1)."""
        n, m = len(bits), self.num_ferns
        b = bits.reshape(n, self.num_tests, m)
        leaves = np.zeros((n, m), np.uint16)
        for j in range(self.num_tests):  # S iterations, each over all N x M ferns
            leaves <<= 1
            leaves |= b[:, j, :]
        return leaves

    def rows_of(self, leaves: npt.ArrayLike) -> IntArray:
        """(N, M) leaves -> (N, M) int64 model rows ``m K + k``; ValueError if out of range."""
        lv = np.asarray(leaves)
        if lv.ndim != 2 or lv.shape[1] != self.num_ferns:
            raise ValueError(f"leaves: expected (N, {self.num_ferns}), got {lv.shape}")
        if lv.size and (lv.min() < 0 or lv.max() >= self.num_leaves):
            raise ValueError(f"leaves must be in [0, {self.num_leaves})")
        return lv.astype(np.int64) + np.arange(self.num_ferns, dtype=np.int64) * self.num_leaves

