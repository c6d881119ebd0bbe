"""Keypoint detection and description (SIFT, ORB) and Lowe ratio-test matching."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from . import hamming
from .errors import ConfigError
from .frame import Features, is_binary_descriptor
from .retain_best import retain_best

FEATURE_KINDS: tuple[str, ...] = ("sift", "orb")


@dataclass(frozen=True)
class FeatureConf:
    """Detector settings. ``max_features`` caps the strongest keypoints kept. ``scale`` below
    1 detects on the image reduced by that factor (area averaging) and reports keypoints in
    the full image's pixels: where blur has removed the fine scales, the reduced image holds
    the same keypoints at a fraction of the cost. ``grid`` above 1 (ORB only) spreads the
    keypoints over a ``grid`` x ``grid`` partition of the image (:func:`spread_over_grid`)
    instead of keeping the strongest wherever they are."""

    kind: str = "sift"
    max_features: int = 2000
    scale: float = 1.0
    grid: int = 1

    def __post_init__(self) -> None:
        if self.kind not in FEATURE_KINDS:
            raise ConfigError(f"feature kind {self.kind!r} unknown; expected one of {FEATURE_KINDS}")
        if self.max_features <= 0:
            raise ConfigError(f"max_features must be positive, got {self.max_features}")
        if not 0 < self.scale <= 1:
            raise ConfigError(f"feature scale must be in (0, 1], got {self.scale}")
        if self.grid < 1 or (self.grid > 1 and self.kind != "orb"):
            raise ConfigError(f"feature grid must be 1, or above 1 for ORB only; got "
                              f"{self.grid} for {self.kind}")

    @property
    def key(self) -> str:
        """The name a frame caches these features under: the kind, with the scale when the
        image is reduced (``"sift@0.5"``) and the grid when they are spread (``"orb#4"``), so
        features of the kind found otherwise stay apart."""
        key = self.kind if self.scale == 1 else f"{self.kind}@{self.scale:g}"
        return key if self.grid == 1 else f"{key}#{self.grid}"


#: Scale step between ORB's pyramid levels (ORB-SLAM's).
ORB_SCALE_FACTOR = 1.2


#: Where OpenCV's SIFT reports a keypoint, pixels in x and y, against the pixel-centre
#: convention (pixel ``i`` covers ``[i - 0.5, i + 0.5]``): its first octave is the image
#: upsampled twice by a centre-aligned linear resize, whose pixel ``u`` lies at ``u / 2 -
#: 0.25`` of the image, while the keypoint is reported at ``u / 2``. Measured on Gaussian
#: blobs at known sub-pixel centres: +0.246 to +0.253 px (tests/test_features.py).
SIFT_UPSCALE_OFFSET_PX = 0.25


def level_scale_factor(kind: str) -> float:
    """Scale step between the pyramid levels that ``Features.levels`` counts: ORB's
    ``ORB_SCALE_FACTOR``, SIFT's octaves 2."""
    if kind not in FEATURE_KINDS:
        raise ConfigError(f"feature kind {kind!r} unknown; expected one of {FEATURE_KINDS}")
    return ORB_SCALE_FACTOR if kind == "orb" else 2.0


def _create(conf: FeatureConf) -> cv2.Feature2D:
    if conf.kind == "sift":
        return cv2.SIFT.create(nfeatures=conf.max_features)
    # FAST threshold low and a patch size suited to 640x480 images; 8 levels as in ORB-SLAM.
    return cv2.ORB.create(nfeatures=conf.max_features, scaleFactor=ORB_SCALE_FACTOR, nlevels=8,
                          fastThreshold=10)


def _features_from_cv(kind: str, keypoints: list[cv2.KeyPoint],
                      descriptors: npt.NDArray | None) -> Features:
    n = len(keypoints)
    width = 128 if kind == "sift" else 32
    # OpenCV's SIFT saturates each value to 0-255 and rounds it (saturate_cast<uchar>) before
    # storing it as float32: the uint8 copy is exact (tests/test_features.py checks it).
    desc = (np.zeros((0, width), np.uint8) if descriptors is None or n == 0
            else descriptors.astype(np.uint8))
    if n == 0:
        return Features.create(kind, np.zeros((0, 2)), desc)
    # cv2.KeyPoint.convert is the vectorised path from keypoint objects to coordinates.
    pts = np.asarray(cv2.KeyPoint.convert(keypoints), np.float64).reshape(-1, 2)
    sizes = np.fromiter((k.size for k in keypoints), np.float32, n)
    angles = np.fromiter((k.angle for k in keypoints), np.float32, n)
    octaves = np.fromiter((k.octave for k in keypoints), np.int64, n)
    levels = (octaves & 0xFF).astype(np.int8).astype(np.int16) if kind == "sift" else octaves.astype(np.int16)
    return Features.create(kind, pts, desc, levels=levels, sizes=sizes, angles=angles)


def extract(image: npt.NDArray[np.uint8], conf: FeatureConf | None = None, *,
            mask: npt.NDArray[np.uint8] | None = None) -> Features:
    """Detect and describe keypoints in a grey (H, W) uint8 image. A detector is created per
    call (cheap) because OpenCV detectors must not be shared between threads."""
    conf = conf or FeatureConf()
    if conf.scale != 1:
        return _extract_reduced(image, conf, mask)
    if conf.grid > 1:
        return _extract_spread(image, conf, mask)
    keypoints, descriptors = _create(conf).detectAndCompute(image, mask)
    return _features_from_cv(conf.kind, list(keypoints), descriptors)


#: The ``Frame.cache`` key of a step's :class:`SiftDetection` of the whole query image, left
#: for :func:`capped` (ferns leaves its own).
SIFT_DETECTED = "features:sift-detected"


@dataclass(frozen=True)
class SiftDetection:
    """Every keypoint ``cv2.SIFT`` (default settings, no cap) finds on an image, in its
    order, with its descriptor (None when there is no keypoint)."""

    keypoints: list[cv2.KeyPoint]
    descriptors: npt.NDArray[np.float32] | None


def detect_sift(image: npt.NDArray[np.uint8]) -> SiftDetection:
    """:class:`SiftDetection` of ``image``: its keypoints and descriptors are those
    ``extract`` keeps of it (same pyramid, same detection; the cap only drops keypoints)."""
    keypoints, descriptors = cv2.SIFT.create().detectAndCompute(image, None)
    return SiftDetection(list(keypoints), None if descriptors is None
                         else np.asarray(descriptors, np.float32))


def capped(image: npt.NDArray[np.uint8], detection: SiftDetection,
           conf: FeatureConf) -> Features:
    """``extract(image, conf)`` for SIFT, from ``detection`` of ``image``, without detecting
    and describing again: the keypoints ``extract``'s cap keeps, in its order
    (:func:`.retain_best.retain_best`), with their descriptors. ``extract`` runs where the
    cap's order cannot be had."""
    if conf.kind != "sift" or conf.scale != 1:
        raise ConfigError(f"capped: SIFT features of the full image expected, got "
                          f"{conf.kind} at scale {conf.scale:g}")
    order = retain_best([k.response for k in detection.keypoints], conf.max_features)
    if order is None:
        return extract(image, conf)
    kept = [detection.keypoints[i] for i in order]
    descriptors = None if detection.descriptors is None else detection.descriptors[order]
    return _features_from_cv(conf.kind, kept, descriptors)


#: Candidates detected per keypoint kept when keypoints are spread over a grid: enough that
#: a cell of the grid whose corners are weaker than elsewhere's still holds candidates.
SPREAD_OVERSAMPLING = 4


def _extract_spread(image: npt.NDArray[np.uint8], conf: FeatureConf,
                    mask: npt.NDArray[np.uint8] | None) -> Features:
    """ORB keypoints spread over the image: ``SPREAD_OVERSAMPLING`` times
    ``conf.max_features`` candidates detected, ``conf.max_features`` of them kept by
    :func:`spread_over_grid`, and only those described."""
    wide = FeatureConf(conf.kind, conf.max_features * SPREAD_OVERSAMPLING)
    candidates = list(_create(wide).detect(image, mask))
    if not candidates:
        return _features_from_cv(conf.kind, [], None)
    n = len(candidates)
    pts = np.asarray(cv2.KeyPoint.convert(candidates), np.float64).reshape(-1, 2)
    levels = np.fromiter((k.octave for k in candidates), np.int64, n)
    response = np.fromiter((k.response for k in candidates), np.float64, n)
    keep = spread_over_grid(pts, levels, response, image.shape[:2], grid=conf.grid,
                            level_quota=orb_level_quota(conf.max_features))
    keypoints, descriptors = _create(conf).compute(image, [candidates[i] for i in keep])
    return _features_from_cv(conf.kind, list(keypoints), descriptors)


def orb_level_quota(count: int, levels: int = 8) -> npt.NDArray[np.int64]:
    """(levels,) keypoints OpenCV's ORB keeps at each pyramid level out of ``count``: a
    geometric series of ratio ``1 / ORB_SCALE_FACTOR`` (a level's share of the image area
    falls by the square, of its perimeter by the factor: ORB's compromise), the remainder at
    the coarsest level."""
    ratio = 1.0 / ORB_SCALE_FACTOR
    first = count * (1 - ratio) / (1 - ratio ** levels)
    quota = np.round(first * ratio ** np.arange(levels)).astype(np.int64)
    quota[-1] = max(0, count - int(quota[:-1].sum()))
    return quota


def spread_over_grid(points_px: npt.NDArray[np.float64], levels: npt.NDArray[np.int64],
                     response: npt.NDArray[np.float64], shape: tuple[int, int], *, grid: int,
                     level_quota: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Indices of the keypoints kept so that each pyramid level keeps ``level_quota[level]``
    of them, shared equally between the ``grid`` x ``grid`` cells of the (H, W) image
    ``shape`` (strongest ``response`` first in each cell), the share a cell cannot fill given
    to the level's strongest remaining keypoints. Corners cluster where the texture is
    sharpest (under motion blur one textured object holds most of them); a pose resting on
    one cluster is weakly conditioned, and the verification refuses inliers covering too
    little of the image, so the keypoints are spread first, as ORB-SLAM's grid does."""
    h, w = shape
    cx = np.clip((points_px[:, 0] * grid / w).astype(np.int64), 0, grid - 1)
    cy = np.clip((points_px[:, 1] * grid / h).astype(np.int64), 0, grid - 1)
    lev = np.clip(levels, 0, len(level_quota) - 1)
    group = lev * grid * grid + cy * grid + cx
    share = -(-level_quota // (grid * grid))  # ceil: a level's share of one cell
    order = np.lexsort((-response, group))
    first = _rank_within(group[order]) < share[lev[order]]
    # each level: its cells' shares first, then its strongest others, up to its quota
    order = order[np.lexsort((-response[order], ~first, lev[order]))]
    kept = order[_rank_within(lev[order]) < level_quota[lev[order]]]
    return np.sort(kept)


def _rank_within(sorted_keys: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Each element's position within its run of equal values of the sorted ``sorted_keys``."""
    n = len(sorted_keys)
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    run_start = np.repeat(starts, np.diff(np.r_[starts, n]))
    return np.arange(n) - run_start


def _extract_reduced(image: npt.NDArray[np.uint8], conf: FeatureConf,
                     mask: npt.NDArray[np.uint8] | None) -> Features:
    """:func:`extract` on ``image`` reduced by ``conf.scale`` (INTER_AREA: each pixel the mean
    of the pixels it covers), keypoints, sizes and pyramid levels mapped back to the full
    image: a keypoint of the reduced image lies at ``(x + 0.5) / scale - 0.5`` and is located
    to ``1 / scale`` full-image pixels, which the level (``factor^level``) carries.

    SIFT's coordinates carry :data:`SIFT_UPSCALE_OFFSET_PX` in whichever image it runs on, so
    that offset is taken out before the mapping and put back after it: the reduced image's
    keypoints then share full-size SIFT's convention, which the map's landmarks were made
    with (without it they sit ``offset * (1 / scale - 1)`` further, +0.25 px at half size)."""
    h, w = image.shape[:2]
    size = (max(1, round(w * conf.scale)), max(1, round(h * conf.scale)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    small_mask = None if mask is None else cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
    keypoints, descriptors = _create(FeatureConf(conf.kind, conf.max_features)).detectAndCompute(
        small, small_mask)
    feats = _features_from_cv(conf.kind, list(keypoints), descriptors)
    sx, sy = w / size[0], h / size[1]
    shift = round(np.log(1.0 / conf.scale) / np.log(level_scale_factor(conf.kind)))
    offset = SIFT_UPSCALE_OFFSET_PX if conf.kind == "sift" else 0.0
    full_px = (feats.keypoints_px - offset + 0.5) * (sx, sy) - 0.5 + offset
    return Features.create(conf.kind, full_px,
                           feats.descriptors, levels=feats.levels + shift,
                           sizes=feats.sizes * np.float32(sx), angles=feats.angles)


def compute_at(image: npt.NDArray[np.uint8], kind: str, keypoints_px: npt.ArrayLike, *,
               size: float = 12.0) -> tuple[Features, npt.NDArray[np.int64]]:
    """Describe given keypoint positions (e.g. SVO's features). Returns the features and, for
    each, the index of the input keypoint it came from (OpenCV drops keypoints too close to the
    border)."""
    pts = np.asarray(keypoints_px, dtype=np.float64).reshape(-1, 2)
    kps = [cv2.KeyPoint(float(x), float(y), size, -1.0, 0.0, 0, i) for i, (x, y) in enumerate(pts)]
    kept, desc = _create(FeatureConf(kind=kind)).compute(image, kps)
    origin = np.fromiter((k.class_id for k in kept), np.int64, len(kept))
    return _features_from_cv(kind, list(kept), desc), origin


def match_ratio(desc_query: npt.NDArray, desc_train: npt.NDArray, *, ratio: float = 0.8
                ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """Lowe's ratio test (thesis 3.1.3): for each query descriptor, its nearest train
    descriptor if the nearest is closer than ``ratio`` times the second nearest.

    Returns (query indices, train indices, distances), each (M,). Binary (uint8) descriptors use
    the Hamming distance, SIFT descriptors (uint8 or float) L2."""
    if len(desc_query) == 0 or len(desc_train) < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0, np.float32)
    dist, nidx = nearest_two(desc_query, desc_train)
    keep = dist[:, 0] < ratio * dist[:, 1]
    q = np.flatnonzero(keep)
    return q.astype(np.int64), nidx[keep, 0].astype(np.int64), dist[keep, 0].astype(np.float32)


def nearest_two(desc_query: npt.NDArray, desc_train: npt.NDArray
                ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """(N, 2) distances and (N, 2) indices of the two nearest train descriptors (at least
    two) of each query descriptor: Hamming for binary (uint8) descriptors, L2 for SIFT."""
    if is_binary_descriptor(desc_query):  # ORB's packed bits: Hamming distance
        return hamming.knn2(desc_query, desc_train)
    d2, nidx = _knn2_squared(desc_query.astype(np.float32), desc_train.astype(np.float32))
    return np.sqrt(d2), nidx


def descriptor_distance(a: npt.NDArray, b: npt.NDArray) -> npt.NDArray[np.float64]:
    """(N,) distances between rows ``a[i]`` and ``b[i]``, as :func:`nearest_two` measures."""
    if is_binary_descriptor(a):
        x, y = np.ascontiguousarray(a), np.ascontiguousarray(b)
        if x.shape[1] % 8 == 0:  # popcount of 64-bit words: 8x fewer than of bytes
            x, y = x.view(np.uint64), y.view(np.uint64)
        return np.bitwise_count(x ^ y).sum(axis=1, dtype=np.int64).astype(np.float64)
    diff = a.astype(np.float32) - b.astype(np.float32)
    return np.sqrt((diff * diff).sum(1)).astype(np.float64)


def _knn2_squared(a: npt.NDArray[np.float32], b: npt.NDArray[np.float32], *,
                  chunk_elems: int = 1 << 22
                  ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """Two nearest neighbours by squared L2: one BLAS product (|a|^2 + |b|^2 - 2 a.b), then two
    argmin passes (cheaper than argpartition); query rows in chunks to bound memory. The
    product is taken of ``-2 a``: a power of two scales every partial sum exactly, so the
    result is the product's times -2 to the bit, without a pass over the (N, M) result."""
    bb = (b * b).sum(1)
    out_d = np.empty((len(a), 2), np.float32)
    out_i = np.empty((len(a), 2), np.int64)
    step = max(1, chunk_elems // len(b))
    scaled = a * np.float32(-2.0)
    for s in range(0, len(a), step):
        g = scaled[s:s + step] @ b.T
        g += bb
        rows = np.arange(len(g))
        i1 = g.argmin(1)
        d1 = g[rows, i1].copy()
        g[rows, i1] = np.inf
        i2 = g.argmin(1)
        out_d[s:s + step, 0], out_d[s:s + step, 1] = d1, g[rows, i2]
        out_i[s:s + step, 0], out_i[s:s + step, 1] = i1, i2
    out_d += (a * a).sum(1)[:, None]
    return np.maximum(out_d, 0.0), out_i
