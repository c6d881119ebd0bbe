"""The vocabulary tree of the bag-of-words place finder (Nister and Stewenius 2006): a
hierarchical k-means tree (k-means++ seeding, a few Lloyd iterations per node) over descriptors,
L2 on float ones (SIFT), Hamming distance with k-majority centres on binary ones (ORB,
Galvez-Lopez and Tardos 2012). A descriptor's visual word is the leaf reached by going down to
the nearest child at every level; all descriptors of a query go down together, one level at a
time. :mod:`.bow` scores keyframes with it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.errors import GeometryError, StorageError
from ...core.frame import is_binary_descriptor

#: Rows per block when descriptors go down the tree (the (rows, k, D) gather stays in cache).
_CHUNK = 1024


# -- distances ---------------------------------------------------------------------------------
def _is_binary(descriptors: npt.NDArray[Any]) -> bool:
    return descriptors.dtype == np.uint8


def _words64(bits: npt.NDArray[np.uint8]) -> npt.NDArray[Any]:
    """Packed bits viewed as 64-bit words along the last axis (8x fewer popcounts), when the
    width allows."""
    if bits.shape[-1] % 8 or not bits.flags.c_contiguous:
        return bits
    return bits.view(np.uint64)


def pairwise_distances(x: npt.NDArray[Any], centres: npt.NDArray[Any],
              x_sq: npt.NDArray[np.float32] | None = None) -> npt.NDArray[np.float32]:
    """(M, K) distances between rows of ``x`` (M, D) and ``centres`` (K, D): squared L2 for
    float descriptors (``x_sq``: the rows' squared norms, if known), Hamming for packed binary
    (uint8) ones."""
    if _is_binary(x):
        xw, cw = _words64(x), _words64(centres)
        out = np.empty((len(x), len(centres)), np.float32)
        for s in range(0, len(x), 32 * _CHUNK):  # bounds the (rows, K, D) XOR temporary
            xor = xw[s:s + 32 * _CHUNK, None, :] ^ cw[None, :, :]
            out[s:s + 32 * _CHUNK] = np.bitwise_count(xor).sum(axis=2, dtype=np.int32)
        return out
    x2 = np.einsum("md,md->m", x, x) if x_sq is None else x_sq
    c2 = np.einsum("kd,kd->k", centres, centres)
    return np.maximum(x2[:, None] + c2[None, :] - 2.0 * (x @ centres.T), 0.0).astype(np.float32)


def _nearest_child(x: npt.NDArray[Any], centres: npt.NDArray[Any],
                   sq_norms: npt.NDArray[np.float32] | None,
                   valid: npt.NDArray[np.bool_]) -> npt.NDArray[np.intp]:
    """For each row of ``x`` (N, D), the index of its nearest row among its own candidate
    ``centres`` (N, K, D) (squared norms ``sq_norms`` (N, K), float only), ignoring slots where
    ``valid`` (N, K) is False."""
    if _is_binary(x):
        xor = _words64(centres) ^ _words64(x)[:, None, :]
        dist = np.bitwise_count(xor).sum(axis=2, dtype=np.int32).astype(np.float32)
    else:
        # |c|^2 - 2 c.x: |x|^2 is common to all children and does not change the argmin.
        dist = sq_norms - 2.0 * np.matmul(centres, x[:, :, None])[:, :, 0]
    dist[~valid] = np.inf
    return np.argmin(dist, axis=1)


# -- k-means of one node -----------------------------------------------------------------------
def _kmeans_pp(x: npt.NDArray[Any], k: int, rng: np.random.Generator,
               x_sq: npt.NDArray[np.float32] | None) -> npt.NDArray[np.intp]:
    """k-means++ seeding (Arthur and Vassilvitskii 2007): up to ``k`` row indices of ``x``,
    each drawn with probability proportional to its squared distance to the nearest seed."""
    def sq_dist(i: int) -> npt.NDArray[np.float64]:
        d = pairwise_distances(x, x[i:i + 1], x_sq)[:, 0].astype(np.float64)
        return d * d if _is_binary(x) else d  # Hamming is a distance, L2 here already squared

    seeds = [int(rng.integers(len(x)))]
    nearest = sq_dist(seeds[0])
    for _ in range(1, k):
        cum = np.cumsum(nearest)
        if cum[-1] <= 0:  # every point coincides with a seed: fewer distinct centres than k
            break
        pick = min(int(np.searchsorted(cum, rng.random() * cum[-1], side="right")), len(x) - 1)
        seeds.append(pick)
        nearest = np.minimum(nearest, sq_dist(pick))
    return np.asarray(seeds, dtype=np.intp)


def _update_centres(x: npt.NDArray[Any], labels: npt.NDArray[np.intp],
                    centres: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """Lloyd update: the mean (float) or bitwise majority (binary, k-majority) of each
    cluster's members; an empty cluster keeps its centre."""
    new = centres.copy()
    # A loop over the k clusters (not the descriptors): measured faster than a membership
    # matrix product, np.add.at or a sorted np.add.reduceat for nodes of 20k+ descriptors.
    for j in range(len(centres)):
        members = x[labels == j]
        if len(members) == 0:
            continue
        if _is_binary(x):
            votes = np.unpackbits(members, axis=1).sum(axis=0, dtype=np.int32)
            new[j] = np.packbits((2 * votes > len(members)).astype(np.uint8))
        else:
            new[j] = members.mean(axis=0, dtype=np.float64)
    return new


def _kmeans(x: npt.NDArray[Any], k: int, iterations: int, rng: np.random.Generator
            ) -> tuple[npt.NDArray[Any], npt.NDArray[np.intp]]:
    """Cluster ``x`` (M, D) into at most ``k`` groups: (centres (K', D), labels (M,)).

    The labels are the nearest centres of the returned centres (the assignment the tree's
    traversal will reproduce); clusters left empty are dropped."""
    x_sq = None if _is_binary(x) else np.einsum("md,md->m", x, x)
    if len(x) <= k:
        centres = x.copy()
    else:
        centres = x[_kmeans_pp(x, k, rng, x_sq)].copy()
        for _ in range(iterations):
            centres = _update_centres(x, np.argmin(pairwise_distances(x, centres, x_sq), axis=1), centres)
    labels = np.argmin(pairwise_distances(x, centres, x_sq), axis=1)
    used = np.flatnonzero(np.bincount(labels, minlength=len(centres)))
    remap = np.full(len(centres), -1, np.intp)
    remap[used] = np.arange(len(used))
    return centres[used], remap[labels]


# -- the tree's size ---------------------------------------------------------------------------
def sized_branching(n_descriptors: int, *, depth: int, max_branching: int,
                    leaf_descriptors: int) -> int:
    """Branching of a ``depth``-level tree sized to ``n_descriptors`` training descriptors:
    the largest k <= ``max_branching`` (at least 2) with ``k ** depth * leaf_descriptors <=
    n_descriptors``, so that a leaf holds ``leaf_descriptors`` of them on average.

    Why a count per leaf: a leaf's centre is the mean (or bitwise majority) of its members;
    the mean of m members is off the cluster's own centre by sigma^2 / m in expectation, so
    a new member's expected squared distance to it is (1 + 1/m) times its distance to the
    true centre: 5 % more at m = 20. A fixed tree of 10^4 leaves trained on a small map's
    20,000 descriptors holds 2 of them per leaf (the leaf is a descriptor, not a word) while
    costing as many centres as a large map's. At the default training cap (200,000
    descriptors) and 20 per leaf the rule gives the fixed tree, 10 ** 4 leaves."""
    if n_descriptors < 0 or depth < 1 or max_branching < 2 or leaf_descriptors < 1:
        raise ValueError(f"sized_branching: expected n >= 0, depth >= 1, max_branching >= 2, "
                         f"leaf_descriptors >= 1; got {n_descriptors}, {depth}, "
                         f"{max_branching}, {leaf_descriptors}")
    k = max_branching
    while k > 2 and k ** depth * leaf_descriptors > n_descriptors:
        k -= 1
    return k


# -- the vocabulary tree -----------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class VocabularyTree:
    """A hierarchical k-means tree. Level l holds ``centres[l]`` (n_l, k, D) and
    ``children[l]`` (n_l, k) int32: the child node's index in level l + 1 (at the last level,
    the visual word id), -1 for an unused slot. Level 0 has one node, the root."""

    centres: tuple[npt.NDArray[Any], ...]
    children: tuple[npt.NDArray[np.int32], ...]
    n_words: int
    _sq_norms: tuple[npt.NDArray[np.float32] | None, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # Squared centre norms (n_l, k) for the L2 traversal, computed once.
        object.__setattr__(self, "_sq_norms", tuple(
            np.einsum("nkd,nkd->nk", c, c, dtype=np.float32) if c.dtype != np.uint8 else None
            for c in self.centres))

    @property
    def depth(self) -> int:
        return len(self.centres)

    @property
    def branching(self) -> int:
        return int(self.children[0].shape[1])

    @property
    def dim(self) -> int:
        return int(self.centres[0].shape[2])

    @property
    def dtype(self) -> np.dtype[Any]:
        return self.centres[0].dtype

    @classmethod
    def build(cls, descriptors: npt.NDArray[Any], *, branching: int, depth: int,
              iterations: int, rng: np.random.Generator) -> VocabularyTree:
        """Hierarchical k-means of ``descriptors`` (M, D) (float32 or uint8), breadth first."""
        x = _as_descriptors(descriptors)
        if len(x) == 0:
            raise GeometryError("vocabulary tree: no descriptors to build from")
        members = [np.arange(len(x))]
        centres, children = [], []
        for _ in range(depth):
            lvl_centres = np.zeros((len(members), branching, x.shape[1]), x.dtype)
            lvl_children = np.full((len(members), branching), -1, np.int32)
            next_members: list[npt.NDArray[np.intp]] = []
            for node, idx in enumerate(members):  # one k-means per node (not per descriptor)
                c, labels = _kmeans(x[idx], branching, iterations, rng)
                lvl_centres[node, :len(c)] = c
                first = len(next_members)
                lvl_children[node, :len(c)] = np.arange(first, first + len(c))
                order = np.argsort(labels, kind="stable")
                next_members.extend(np.split(idx[order], np.cumsum(np.bincount(labels))[:-1]))
            centres.append(lvl_centres)
            children.append(lvl_children)
            members = next_members
        return cls(tuple(centres), tuple(children), len(members))

    def quantise(self, descriptors: npt.NDArray[Any]) -> npt.NDArray[np.int32]:
        """(N,) visual word of each descriptor (N, D): all descriptors descend together, level
        by level, to their nearest child."""
        x = _as_descriptors(descriptors)
        if x.shape[1] != self.dim or x.dtype != self.dtype:
            raise GeometryError(f"vocabulary tree: expected ({self.dim},) {self.dtype} "
                                f"descriptors, got {x.shape[1:]} {x.dtype}")
        words = np.empty(len(x), np.int32)
        for s in range(0, len(x), _CHUNK):
            block = x[s:s + _CHUNK]
            node: npt.NDArray[Any] = np.zeros(len(block), np.intp)
            for centres, norms, children in zip(self.centres, self._sq_norms, self.children,
                                                strict=True):
                kids = children[node]
                slot = _nearest_child(block, centres[node], None if norms is None else norms[node],
                                      kids >= 0)
                node = kids[np.arange(len(block)), slot]
            words[s:s + _CHUNK] = node
        return words

    def to_state(self, *, centres: str = "float16") -> dict[str, Any]:
        """msgpack-able description (shapes, dtype, raw bytes of each level). Float centres
        (means of SIFT's integer values 0-255) are stored as float16: within 0.06 of the
        float32 mean (half a unit in the last place at 128-256), a hundredth of the distance
        between two descriptors' values that round apart, at half the bytes. With ``centres
        == "uint8"`` (and every centre within 0-255) they are rounded to SIFT's own integer
        grid instead, half float16's bytes again: each value within 0.5, a centre within 5.7
        (3.3 RMS) in L2 over 128 values, which moves a descriptor's distance to it by no more
        (triangle inequality); two views' SIFT descriptors of one point (OpenCV's, integer
        values, norm 512) lie 90-240 apart (10th-90th percentile of ratio-test matches
        between two desk keyframes, median 165), so a descriptor changes word only where its
        own noise already decides it.
        Any reader of float16 centres reads them (``stored_dtype``)."""
        if centres not in ("float16", "uint8"):
            raise ValueError(f"vocabulary centres: expected 'float16' or 'uint8', got "
                             f"{centres!r}")
        stored = np.dtype(np.float16) if self.dtype == np.float32 else self.dtype
        if centres == "uint8" and self.dtype == np.float32 and all(
                c.size == 0 or (c.min() >= 0 and c.max() <= 255) for c in self.centres):
            stored = np.dtype(np.uint8)
        return {"dtype": str(self.dtype), "stored_dtype": str(stored), "dim": self.dim,
                "branching": self.branching, "n_words": self.n_words,
                "levels": [{"nodes": int(len(c)),
                            "centres": _stored_centres(c, stored).tobytes(),
                            "children": np.ascontiguousarray(ch).tobytes()}
                           for c, ch in zip(self.centres, self.children, strict=True)]}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> VocabularyTree:
        """Inverse of :meth:`to_state`; StorageError if the sizes do not add up."""
        try:
            dtype = np.dtype(state["dtype"])
            stored = np.dtype(state.get("stored_dtype", dtype))   # older states: as held
            dim, k = int(state["dim"]), int(state["branching"])
            centres, children = [], []
            for level in state["levels"]:
                n = int(level["nodes"])
                centres.append(np.frombuffer(level["centres"], stored).reshape(n, k, dim)
                               .astype(dtype))
                children.append(np.frombuffer(level["children"], np.int32).reshape(n, k).copy())
            tree = cls(tuple(centres), tuple(children), int(state["n_words"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise StorageError(f"bow state: damaged vocabulary tree ({exc})") from exc
        if not centres or int(children[-1].max(initial=-1)) >= tree.n_words:
            raise StorageError("bow state: vocabulary tree has no level or a word id out of range")
        return tree


def _stored_centres(centres: npt.NDArray[Any], stored: np.dtype[Any]) -> npt.NDArray[Any]:
    """A level's centres in the ``stored`` dtype: rounded to the nearest integer for uint8
    from float (a cast alone would truncate), else converted."""
    if stored == np.uint8 and centres.dtype != np.uint8:
        return np.ascontiguousarray(np.rint(centres), np.uint8)
    return np.ascontiguousarray(centres, stored)


def _as_descriptors(descriptors: npt.NDArray[Any]) -> npt.NDArray[Any]:
    d = np.asarray(descriptors)
    if d.ndim != 2:
        raise GeometryError(f"descriptors: expected (N, D), got shape {d.shape}")
    # SIFT (uint8 or float) is clustered in float32 (L2 means); ORB stays packed bits.
    return np.ascontiguousarray(d if is_binary_descriptor(d) else
                                d.astype(np.float32, copy=False))
