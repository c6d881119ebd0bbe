"""Product quantization of SIFT descriptors for snapshots (Jegou, Douze and Schmid 2011).

A 128-dimensional uint8 SIFT descriptor is cut into :data:`SUBSPACES` sub-vectors of
``128 / SUBSPACES`` values; each is replaced by the index (one byte) of its nearest of 256
centroids learnt for that sub-vector by k-means on the map's own descriptors. A snapshot stores
the (N, SUBSPACES) uint8 codes and the (SUBSPACES, 256, 128 / SUBSPACES) uint8 codebook instead
of the (N, 128) descriptors.

Reading decodes (each sub-vector becomes its centroid): matching a full-precision query
descriptor against a decoded one is the asymmetric distance of PQ (the query is not quantized),
computed by the matchers already there. The centroids are rounded to uint8, so a decoded
descriptor is a valid SIFT descriptor and encoding it again with the same codebook gives it back
unchanged: a map saved, loaded and saved again loses nothing more at the second save.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from threadpoolctl import threadpool_limits

from ..core.errors import StorageError
from ..core.frame import Features

#: The (N, M) uint8 codes a snapshot stores instead of a kind's descriptors (feature column
#: name), and the (M, 256, D / M) uint8 codebook they decode with (format 6).
DESCRIPTOR_CODES = "descriptors_pq"
CODEBOOK = "pq_codebook"
#: Bytes per coded descriptor (sub-vectors of 128 / SUBSPACES values, 8-bit codes).
SUBSPACES = 32
#: Sub-quantizers of each PQ codec (``[service] descriptor_codec``): "pq" codes a SIFT
#: descriptor in 32 bytes (4-value sub-vectors), "pq16" in 16 (8-value sub-vectors, half the
#: bytes, coarser). A snapshot's codebook records its own M, so a reader needs no codec name.
CODEC_SUBSPACES = {"pq": SUBSPACES, "pq16": 16, "pq-hybrid": SUBSPACES}
#: Codecs that keep a row in full where its code's error exceeds the descriptors' own noise
#: (:mod:`.descriptor_hybrid`; the codebook carries the threshold).
EXACT_CODECS = ("pq-hybrid",)
CENTROIDS = 256
#: Descriptors a codebook is learnt from (64 per centroid; a seeded draw when the map holds
#: more), and the fewest it is learnt from: below this a k-means of 256 centroids per
#: sub-vector has fewer than 16 samples per centroid, and the descriptors are stored in full.
TRAIN_SAMPLES = 16384
MIN_TRAIN_SAMPLES = TRAIN_SAMPLES
KMEANS_ITERATIONS = 12
#: Rows encoded at once (bounds the (rows, 256) distance block of each sub-vector).
_CHUNK = 8192


@dataclass(frozen=True, eq=False)
class PQCodebook:
    """(SUBSPACES, 256, D / SUBSPACES) uint8 centroids of a product quantizer of D-dim descriptors."""

    centroids: npt.NDArray[np.uint8]
    #: squared L2 error of a code beyond which its row is also stored in full (None: never;
    #: :mod:`.descriptor_hybrid`)
    exact_above: float | None = None
    #: codes of the Features objects already coded (a map saved every few hundred puts codes
    #: each keyframe once, not at every save); gone with the Features
    _memo: weakref.WeakKeyDictionary[Features, npt.NDArray[np.uint8]] = field(
        default_factory=weakref.WeakKeyDictionary, repr=False)

    def __post_init__(self) -> None:
        c = self.centroids
        if c.dtype != np.uint8 or c.ndim != 3 or c.shape[1] != CENTROIDS or c.shape[0] < 1:
            raise StorageError(f"PQ codebook: expected (M, {CENTROIDS}, D/M) uint8 centroids, "
                               f"got {c.shape} {c.dtype}")

    @property
    def subspaces(self) -> int:
        """Sub-quantizers M (bytes per code)."""
        return int(self.centroids.shape[0])

    @property
    def width(self) -> int:
        """Descriptor length D."""
        return int(self.centroids.shape[0] * self.centroids.shape[2])

    def encode(self, descriptors: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """(N, M) uint8 codes of (N, D) descriptors: per sub-vector, the nearest centroid (L2)."""
        m = self.centroids.shape[0]
        if descriptors.ndim != 2 or descriptors.shape[1] != self.width:
            raise ValueError(f"descriptors: expected (N, {self.width}), got {descriptors.shape}")
        cents = self.centroids.astype(np.float32)
        c2 = (cents * cents).sum(2)                                  # (M, 256)
        codes = np.empty((len(descriptors), m), np.uint8)
        with threadpool_limits(limits=1, user_api="blas"):   # see train_codebook
            for s in range(0, len(descriptors), _CHUNK):
                self._encode_rows(descriptors[s:s + _CHUNK], cents, c2, codes[s:s + _CHUNK])
        return codes

    @staticmethod
    def _encode_rows(rows: npt.NDArray[np.uint8], cents: npt.NDArray[np.float32],
                     c2: npt.NDArray[np.float32], out: npt.NDArray[np.uint8]) -> None:
        m, _, ds = cents.shape
        # (M, rows, D/M): each sub-vector contiguous, so each product is one BLAS call
        x = np.ascontiguousarray(rows.astype(np.float32).reshape(-1, m, ds).transpose(1, 0, 2))
        for j in range(m):   # |x|^2 does not change the argmin
            d = x[j] @ (-2.0 * cents[j].T)
            d += c2[j]
            out[:, j] = d.argmin(1)

    def encode_features(self, features: Features) -> npt.NDArray[np.uint8]:
        """:meth:`encode` of ``features.descriptors``, computed once per Features object."""
        codes = self._memo.get(features)
        if codes is None:
            codes = self._memo[features] = self.encode(np.asarray(features.descriptors))
        return codes

    def decode(self, codes: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """(N, D) uint8 descriptors of (N, M) codes (each sub-vector its centroid)."""
        m = self.centroids.shape[0]
        if codes.ndim != 2 or codes.shape[1] != m:
            raise StorageError(f"PQ codes: expected (N, {m}), got {codes.shape}")
        # one gather from the (M * 256, D / M) table: row 256 j + code of sub-vector j
        # (equal to ``centroids[arange(M), codes]``, 1.5x (M = 32) to 7x (M = 16) faster)
        table = self.centroids.reshape(m * CENTROIDS, -1)
        rows = codes.astype(np.intp) + np.arange(0, m * CENTROIDS, CENTROIDS)
        return np.take(table, rows, axis=0).reshape(len(codes), self.width)


def train_codebook(descriptors: npt.NDArray[np.uint8], *, subspaces: int = SUBSPACES,
                   seed: int = 0) -> PQCodebook | None:
    """A codebook learnt on (N, D) uint8 descriptors (up to :data:`TRAIN_SAMPLES`, a seeded
    draw); None when fewer than :data:`MIN_TRAIN_SAMPLES` are given (too few to learn 256
    centroids per sub-vector from: the caller stores them in full)."""
    n, width = descriptors.shape
    if width % subspaces:
        raise ValueError(f"descriptor length {width} is not a multiple of {subspaces} sub-vectors")
    if n < MIN_TRAIN_SAMPLES:
        return None
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(n, TRAIN_SAMPLES, replace=False)) if n > TRAIN_SAMPLES else None
    sample = (descriptors if pick is None else descriptors[pick]).astype(np.float32)
    parts = sample.reshape(len(sample), subspaces, width // subspaces)
    # products of inner dimension D/M are too small to share among BLAS threads: one
    # thread is 5x faster than two on a busy 2-core machine
    with threadpool_limits(limits=1, user_api="blas"):
        cents = np.stack([_kmeans(np.ascontiguousarray(parts[:, j]), rng)
                          for j in range(subspaces)])
    return PQCodebook(np.clip(np.rint(cents), 0, 255).astype(np.uint8))


def seeded_rows(per_keyframe: list[npt.NDArray[np.uint8]], *, limit: int = TRAIN_SAMPLES,
                seed: int = 0) -> npt.NDArray[np.uint8]:
    """Up to ``limit`` rows of the keyframes' (N_i, D) descriptors (a seeded draw when they
    hold more), gathered keyframe by keyframe (never every row concatenated)."""
    per_keyframe = [d for d in per_keyframe if len(d)]
    if not per_keyframe:
        return np.zeros((0, 128), np.uint8)
    ends = np.cumsum([len(d) for d in per_keyframe])
    if ends[-1] <= limit:
        return np.concatenate(per_keyframe)
    pick = np.sort(np.random.default_rng(seed).choice(ends[-1], limit, replace=False))
    groups = np.split(pick, np.searchsorted(pick, ends[:-1]))
    starts = ends - [len(d) for d in per_keyframe]
    return np.concatenate([d[g - s] for d, g, s in zip(per_keyframe, groups, starts,
                                                        strict=True)])


def _kmeans(x: npt.NDArray[np.float32], rng: np.random.Generator) -> npt.NDArray[np.float32]:
    """(256, d) Lloyd centroids of (n, d) points, seeded with distinct sample points; an
    emptied centroid is moved to the point farthest from its own centroid."""
    cents = x[rng.choice(len(x), CENTROIDS, replace=False)].copy()
    x2 = (x * x).sum(1)
    for _ in range(KMEANS_ITERATIONS):
        d = x @ (-2.0 * cents.T)
        d += (cents * cents).sum(1)
        label = d.argmin(1)
        counts = np.bincount(label, minlength=CENTROIDS)
        sums = np.stack([np.bincount(label, x[:, k], CENTROIDS) for k in range(x.shape[1])],
                        axis=1)
        filled = counts > 0
        cents[filled] = sums[filled] / counts[filled, None]
        if not filled.all():
            err = x2 + d[np.arange(len(x)), label]
            far = np.argsort(err)[::-1][: int((~filled).sum())]
            cents[~filled] = x[far]
    return cents


def descriptor_rows(part: Features | dict[str, np.ndarray], source: PQCodebook | None,
                     target: PQCodebook | None) -> np.ndarray:
    """A part's descriptors as ``target`` codes them (as they are without one): codes coded
    by ``target`` already are copied, never decoded and coded again."""
    if isinstance(part, Features):
        if target is not None:
            return target.encode_features(part)
        desc = part.descriptors
    elif DESCRIPTOR_CODES in part:
        if source is not None and source is target:
            return part[DESCRIPTOR_CODES]
        assert source is not None, "coded rows come with their codebook"
        desc = source.decode(part[DESCRIPTOR_CODES])
    else:
        desc = part["descriptors"]
    return desc if target is None else target.encode(np.asarray(desc))
