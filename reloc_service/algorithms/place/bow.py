"""Bag-of-words place finder: a vocabulary tree (Nister and Stewenius 2006) over the map's own
keyframe descriptors, tf-idf weights, L1 scoring through a sparse inverted file.

The vocabulary is a hierarchical k-means tree (:mod:`.vocabulary`; k-means++ seeding, a few
Lloyd iterations per node): L2 on float descriptors (SIFT), Hamming distance with k-majority
centres on binary ones (ORB, Galvez-Lopez and Tardos 2012). A descriptor's visual word is the
leaf reached by going down to the nearest child at every level; all descriptors of a query go
down together, one level at a time. A keyframe's vector holds ``count(word) * idf(word)``,
``idf = ln(N / n_word)`` over the N indexed keyframes, L1-normalised; a query is scored against
keyframe d by Nister's normalised L1 difference ``|q - d|_1 = 2 - 2 sum_w min(q_w, d_w)``,
reported as the similarity ``sum_w min(q_w, d_w)`` in [0, 1] (higher is more similar).

Training. :meth:`BagOfWords.train` builds the vocabulary from the map's keyframes (descriptors
subsampled to ``max_train_descriptors``, seeded) and indexes every keyframe, however few there
are (any number of descriptors makes a tree). The tree is ``branching ** depth`` leaves
whatever the map holds, or, with ``leaf_descriptors`` set, sized to the map's training
descriptors (:func:`.vocabulary.sized_branching`: as many leaves as leave each that many
descriptors on average, up to the fixed tree). Before training, ``add_keyframe`` has nothing to do
(training reads the map) and ``find_places`` raises :class:`NotTrainedError` rather than
building a vocabulary inside a query (seconds for a large map; a fallback chain then moves on
to its next method); on an empty map it returns no candidates.
Keyframes without features of ``kind`` are described on the fly (cached in the keyframe's
``cache``). Keyframes added after
training are quantised with the existing tree (the vocabulary is not rebuilt; call ``train()``
again after the map has grown a lot), and idf weights follow every addition and removal.

Threads. No lock: the finder is used behind the engine, whose write lock keeps map updates
apart from queries. Queries may run concurrently; the one thing they write is the weighted
inverted file, rebuilt lazily on the first query after a change (rebuilding it on every
keyframe would cost O(K) per keyframe, O(K^2) to load a map). Two queries racing there build
the same index from the same rows and each keeps its own reference, so the race only costs a
duplicate build.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from ...core.errors import ConfigError, NotTrainedError, StorageError
from ...core.features import FEATURE_KINDS, FeatureConf, extract
from ...core.frame import Features, Frame, Keyframe
from ...core.landmark_rows import check_every_row
from ...core.map import KeyframeMap
from ...core.numeric import top_k
from .base import PlaceCandidate, PlaceFinder, register
from .vocabulary import VocabularyTree, sized_branching

_STATE_FORMAT = 1


# -- the inverted file -------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class InvertedFile:
    """Weighted inverted file of one map version: ``weights`` (K, W) CSC, L1-normalised rows."""

    keyframe_ids: npt.NDArray[np.int64]
    weights: sp.csc_matrix
    idf: npt.NDArray[np.float64]


def _bag(words: npt.NDArray[np.int32]) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]:
    """Distinct words (ascending) and how often each occurs."""
    uniq, counts = np.unique(words, return_counts=True)
    return uniq.astype(np.int32), counts.astype(np.float32)


def _build_index(rows: dict[int, tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]],
                 n_words: int) -> InvertedFile:
    """tf-idf weights of every keyframe from its word counts; idf = ln(N / n_word)."""
    ids = np.fromiter(sorted(rows), np.int64, len(rows))
    words = [rows[int(i)][0] for i in ids]
    counts = [rows[int(i)][1] for i in ids]
    indptr = np.concatenate([[0], np.cumsum([len(w) for w in words])]).astype(np.int64)
    cat_words = np.concatenate(words) if words else np.zeros(0, np.int32)
    cat_counts = np.concatenate(counts) if counts else np.zeros(0, np.float32)
    doc_freq = np.bincount(cat_words, minlength=n_words)
    with np.errstate(divide="ignore"):
        idf = np.where(doc_freq > 0, np.log(max(len(ids), 1) / np.maximum(doc_freq, 1)), 0.0)
    tfidf = sp.csr_matrix((cat_counts * idf[cat_words], cat_words, indptr),
                          shape=(len(ids), n_words))
    norms = np.asarray(tfidf.sum(axis=1)).ravel()
    tfidf = sp.diags(np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)) @ tfidf
    return InvertedFile(ids, tfidf.tocsc(), idf)


def l1_scores(index_weights: sp.csc_matrix, query_words: npt.NDArray[np.int32],
              query_weights: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(K,) similarity ``sum_w min(q_w, d_w)`` of an L1-normalised query (distinct ``query_words``
    with ``query_weights``) to every L1-normalised row of ``index_weights`` (K, W): only the
    inverted lists of the query's words are read (one column slice, one weighted bincount)."""
    lists = index_weights[:, query_words]  # CSC: the inverted file of the query's words
    word_of_entry = np.repeat(np.arange(len(query_words)), np.diff(lists.indptr))
    common = np.minimum(lists.data, query_weights[word_of_entry])
    scores = np.bincount(lists.indices, weights=common, minlength=index_weights.shape[0])
    return scores.astype(np.float64, copy=False)


# -- the place finder --------------------------------------------------------------------------
@register("bow")
class BagOfWords(PlaceFinder):
    """Vocabulary-tree bag of words (Nister and Stewenius 2006): rotation and scale invariant
    through its local features, unlike the small blurry image."""

    required_features: frozenset[str] = frozenset({"sift"})

    @dataclass(frozen=True)
    class Conf:
        #: Feature kind whose descriptors are quantised ("sift": L2, "orb": Hamming).
        kind: str = "sift"
        #: Children per node and levels: up to branching**depth visual words.
        branching: int = 10
        depth: int = 4
        #: Training descriptors per leaf the tree is sized for (:func:`.vocabulary.sized_branching`:
        #: ``depth`` levels, the largest branching up to ``branching`` that leaves each leaf
        #: this many of the map's training descriptors on average); 0: the fixed tree of
        #: ``branching ** depth`` leaves whatever the map holds.
        leaf_descriptors: int = 0
        #: Lloyd iterations per node after k-means++ seeding.
        kmeans_iterations: int = 5
        #: Descriptors drawn (uniformly, seeded) from the map to build the tree.
        max_train_descriptors: int = 200_000
        seed: int = 0
        #: Keypoints extracted from a query that comes without features of ``kind``.
        max_features: int = 2000
        #: Query image scale the query's keypoints are detected at (:class:`FeatureConf`):
        #: 0.5 quantises the half-size image's SIFT, which a chain's ``sift-half`` step has
        #: extracted already (the same cached features, not a second extraction); the
        #: keyframes' words stay those of their full-size features.
        query_scale: float = 1.0

        def __post_init__(self) -> None:
            if self.kind not in FEATURE_KINDS:
                raise ConfigError(f"bow: kind {self.kind!r} unknown; expected one of "
                                  f"{FEATURE_KINDS}")
            if self.branching < 2 or self.depth < 1 or self.kmeans_iterations < 0:
                raise ConfigError(f"bow: expected branching >= 2, depth >= 1, "
                                  f"kmeans_iterations >= 0; got {self.branching}, {self.depth}, "
                                  f"{self.kmeans_iterations}")
            if self.leaf_descriptors < 0:
                raise ConfigError(f"bow: expected leaf_descriptors >= 0 (0: a fixed tree), got "
                                  f"{self.leaf_descriptors}")
            if self.max_train_descriptors < 1 or self.max_features < 1:
                raise ConfigError("bow: max_train_descriptors and max_features must be positive")
            if not 0 < self.query_scale <= 1:
                raise ConfigError(f"bow: expected query_scale in (0, 1], got {self.query_scale}")

    def __init__(self, kmap: KeyframeMap, conf: BagOfWords.Conf) -> None:
        super().__init__(kmap, conf)
        self.conf: BagOfWords.Conf = conf
        # The kind is an option, so the requirement is per instance.
        self.required_features = frozenset({conf.kind})
        self._tree: VocabularyTree | None = None
        self._rows: dict[int, tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]] = {}
        self._index: InvertedFile | None = None  # None: rebuild from _rows on the next query

    # -- model -------------------------------------------------------------------------------
    @property
    def trained(self) -> bool:
        return self._tree is not None

    @property
    def vocabulary(self) -> VocabularyTree | None:
        """The vocabulary tree, None before training."""
        return self._tree

    def indexed_keyframe_ids(self) -> list[int]:
        """Ids of the keyframes in the inverted file, ascending."""
        return sorted(self._rows)

    def train(self) -> None:
        """Build the vocabulary from the map's keyframes and index all of them; a map without
        descriptors of ``kind`` leaves the finder untrained."""
        descriptors = self._training_descriptors()
        if descriptors is None:
            return
        branching = self.conf.branching
        if self.conf.leaf_descriptors:
            branching = sized_branching(len(descriptors), depth=self.conf.depth,
                                        max_branching=branching,
                                        leaf_descriptors=self.conf.leaf_descriptors)
        tree = VocabularyTree.build(descriptors, branching=branching, depth=self.conf.depth,
                                    iterations=self.conf.kmeans_iterations,
                                    rng=np.random.default_rng(self.conf.seed))
        self._install(tree)

    def _install(self, tree: VocabularyTree) -> None:
        """Use ``tree`` and index every keyframe of the map as it is now."""
        self._tree = tree
        self._rows = {}
        for kf in self.map.snapshot().keyframes.values():
            self._index_keyframe(kf)
        self._index = None

    def _training_descriptors(self) -> npt.NDArray[Any] | None:
        """Up to ``max_train_descriptors`` descriptors of the map's keyframes (seeded draw)."""
        per_kf = [f.descriptors for kf in self.map.snapshot().keyframes.values()
                  if len(f := self._keyframe_features(kf))]
        if not per_kf:
            return None
        ends = np.cumsum([len(d) for d in per_kf])
        if ends[-1] <= self.conf.max_train_descriptors:
            return np.concatenate(per_kf)
        # Draw global indices, then gather keyframe by keyframe (never concatenate everything).
        rng = np.random.default_rng(self.conf.seed)
        pick = np.sort(rng.choice(ends[-1], self.conf.max_train_descriptors, replace=False))
        groups = np.split(pick, np.searchsorted(pick, ends[:-1]))
        starts = ends - [len(d) for d in per_kf]
        return np.concatenate([d[g - s] for d, g, s in zip(per_kf, groups, starts, strict=True)])

    def _keyframe_features(self, keyframe: Frame) -> Features:
        """The keyframe's features of ``kind``; extracted once (and cached) when it has none."""
        check_every_row(keyframe, "a bag-of-words vocabulary (its training and indexing)")
        feats = keyframe.features.get(self.conf.kind)
        if feats is None:
            key = f"bow:features:{self.conf.kind}:{self.conf.max_features}"
            if key not in keyframe.cache:
                keyframe.cache[key] = extract(keyframe.image,
                                              FeatureConf(self.conf.kind, self.conf.max_features))
            feats = keyframe.cache[key]
        return feats

    def _index_keyframe(self, keyframe: Keyframe) -> None:
        assert self._tree is not None
        feats = self._keyframe_features(keyframe)
        if len(feats) == 0:
            self._rows.pop(keyframe.id, None)
        else:
            self._rows[keyframe.id] = _bag(self._tree.quantise(feats.descriptors))
        self._index = None

    # -- map updates -------------------------------------------------------------------------
    def add_keyframe(self, keyframe: Keyframe) -> None:
        """Quantise ``keyframe`` with the existing tree and add it to the inverted file
        (replacing an entry with the same id). Before training: nothing to do, training reads
        the map."""
        if self._tree is not None:
            self._index_keyframe(keyframe)

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        """Drop ``keyframe`` from the inverted file (idf counts follow)."""
        if self._rows.pop(keyframe.id, None) is not None:
            self._index = None

    def _current_index(self) -> InvertedFile | None:
        """The weighted inverted file, rebuilt if keyframes changed; None if nothing is
        indexed; NotTrainedError before training on a map with keyframes. Concurrent queries
        may both rebuild it (module docstring): each returns the index it read or built."""
        if self._tree is None:
            if len(self.map):
                raise NotTrainedError(f"bow place finder: not trained; call train() to build "
                                      f"the vocabulary from the {self.conf.kind} descriptors "
                                      f"of the map's {len(self.map)} keyframes")
            return None
        if not self._rows:
            return None
        index = self._index
        if index is None:
            index = self._index = _build_index(self._rows, self._tree.n_words)
        return index

    # -- queries -----------------------------------------------------------------------------
    def feature_confs(self) -> dict[str, FeatureConf]:
        conf = FeatureConf(self.conf.kind, self.conf.max_features, scale=self.conf.query_scale)
        return {conf.key: conf}

    def query_features(self, query: Frame) -> Features:
        """The query's features of ``kind``, extracted and stored in ``query.features`` if
        missing (so a pose finder reuses them; or extracted ahead: :meth:`Frame.features_of`)."""
        (kind, conf), = self.feature_confs().items()
        return query.features_of(kind, lambda: extract(query.image, conf))

    def find_places(self, query: Frame, k: int, *, allowed: set[int] | None = None
                    ) -> list[PlaceCandidate]:
        """Up to ``k`` keyframes sharing visual words with ``query``, most similar first;
        NotTrainedError before :meth:`train` (on a map with keyframes)."""
        index = self._current_index()
        feats = self.query_features(query)
        if index is None or len(feats) == 0 or k <= 0:
            return []
        assert self._tree is not None
        scores = self.score(self._tree.quantise(feats.descriptors), index)
        if allowed is not None:
            scores[~np.isin(index.keyframe_ids, np.fromiter(allowed, np.int64, len(allowed)))] = 0.0
        return _best_candidates(index.keyframe_ids, scores, k)

    @staticmethod
    def score(words: npt.NDArray[np.int32], index: InvertedFile) -> npt.NDArray[np.float64]:
        """(K,) similarity of a query given as its (N,) visual words to every indexed keyframe."""
        uniq, counts = _bag(words)
        weights = counts * index.idf[uniq]
        total = weights.sum()
        if total <= 0:  # only words no keyframe has, or words every keyframe has
            return np.zeros(len(index.keyframe_ids))
        return l1_scores(index.weights, uniq, weights / total)

    # -- persistence -------------------------------------------------------------------------
    def state(self, *, centres: str = "float16") -> dict[str, Any] | None:
        """Vocabulary tree (its float centres stored as ``centres`` says:
        :meth:`VocabularyTree.to_state`) and per-keyframe word counts (msgpack-able), None
        before training."""
        if self._tree is None:
            return None
        ids = sorted(self._rows)
        words = [self._rows[i][0] for i in ids]
        return {"format": _STATE_FORMAT, "kind": self.conf.kind,
                "tree": self._tree.to_state(centres=centres),
                "keyframe_ids": [int(i) for i in ids],
                "indptr": np.cumsum([0] + [len(w) for w in words]).astype(np.int64).tobytes(),
                "words": np.concatenate(words or [np.zeros(0, np.int32)]).tobytes(),
                "counts": np.concatenate([self._rows[i][1] for i in ids]
                                         or [np.zeros(0, np.float32)]).tobytes()}

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state`; when the map already holds keyframes, keyframes it no longer
        has are dropped and keyframes missing from the state are indexed."""
        if state.get("format") != _STATE_FORMAT:
            raise StorageError(f"bow state: format {state.get('format')!r}, "
                               f"expected {_STATE_FORMAT}")
        if state.get("kind") != self.conf.kind:
            raise StorageError(f"bow state was built on {state.get('kind')!r} features but this "
                               f"place finder uses {self.conf.kind!r}")
        tree = VocabularyTree.from_state(state["tree"])
        rows = _rows_from_state(state, tree.n_words)
        self._tree, self._rows, self._index = tree, rows, None
        keyframes = self.map.snapshot().keyframes
        if keyframes:
            for kf_id in set(self._rows) - set(keyframes):
                del self._rows[kf_id]
            for kf_id in set(keyframes) - set(self._rows):
                self._index_keyframe(keyframes[kf_id])


def _rows_from_state(state: dict[str, Any], n_words: int
                     ) -> dict[int, tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]]:
    try:
        ids = [int(i) for i in state["keyframe_ids"]]
        indptr = np.frombuffer(state["indptr"], np.int64)
        words = np.frombuffer(state["words"], np.int32)
        counts = np.frombuffer(state["counts"], np.float32)
    except (KeyError, TypeError, ValueError) as exc:
        raise StorageError(f"bow state: damaged inverted file ({exc})") from exc
    if (len(indptr) != len(ids) + 1 or len(words) != len(counts) or indptr[-1] != len(words)
            or (len(words) and (words.min() < 0 or words.max() >= n_words))):
        raise StorageError("bow state: inverted file sizes or word ids are inconsistent")
    return {kf: (words[a:b].copy(), counts[a:b].copy())
            for kf, a, b in zip(ids, indptr[:-1], indptr[1:], strict=True)}


def _best_candidates(ids: npt.NDArray[np.int64], scores: npt.NDArray[np.float64], k: int
                     ) -> list[PlaceCandidate]:
    """The ``k`` best-scoring ids with a positive score, best first (ties: lower id first)."""
    order = top_k(scores, k, keep=scores > 0, tiebreak=ids)
    return [PlaceCandidate(int(ids[i]), float(scores[i])) for i in order]
