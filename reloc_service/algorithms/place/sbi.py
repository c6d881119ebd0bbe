"""PTAM place finder: small blurry images compared whole (thesis 3.1.1), by normalised
cross-correlation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core.frame import Frame, Keyframe, ThumbnailConf
from ...core.map import KeyframeMap
from ...core.numeric import top_k
from .base import PlaceCandidate, PlaceFinder, register

Thumbs = npt.NDArray[np.float32]


@register("sbi")
class SmallBlurryImageFinder(PlaceFinder):
    """Ranks keyframes by ``-SSD`` between zero-mean, unit-norm 40x30 thumbnails blurred with
    sigma 2.5, i.e. by their normalised cross-correlation (``SSD = 2 - 2 NCC``). PTAM subtracts
    the mean only; dividing by the norm too makes the score invariant to the camera's gain as
    well as to its offset, the first-order model of an exposure change (a query taken with
    another exposure time or auto-gain than the keyframes).

    All keyframe thumbnails live in one contiguous (K, w*h) float32 matrix with their squared
    norms, so scoring every keyframe is one matrix-vector product:
    ``SSD = |a|^2 + |b|^2 - 2 a.b``. Adding appends a row; removing swaps the last row into
    the freed one, so the matrix never has holes.

    Not thread-safe (no lock): used behind the engine, whose write lock keeps adds and removes
    apart from queries; queries only read the matrix, so they may run concurrently.
    """

    @dataclass(frozen=True)
    class Conf(ThumbnailConf):
        pass

    def __init__(self, kmap: KeyframeMap, conf: SmallBlurryImageFinder.Conf) -> None:
        super().__init__(kmap, conf)
        self._dim = conf.width * conf.height
        self._thumbs: Thumbs = np.zeros((16, self._dim), np.float32)
        self._sq_norms = np.zeros(16, np.float32)
        self._ids = np.zeros(16, np.int64)
        self._row_of: dict[int, int] = {}
        self.train()

    def __len__(self) -> int:
        return len(self._row_of)

    def thumbnail(self, frame: Frame) -> Thumbs:
        """(w*h,) float32 zero-mean, unit-norm small blurry image of ``frame`` (zero for a
        flat image)."""
        c = self.conf
        thumb = np.asarray(frame.small_blurry_image(c.width, c.height, c.blur_sigma),
                           np.float32).ravel()
        norm = float(np.linalg.norm(thumb))
        return np.ascontiguousarray(thumb / norm if norm > 1e-6 else np.zeros_like(thumb))

    def add_keyframe(self, keyframe: Keyframe) -> None:
        """Index ``keyframe``; a keyframe with an id already indexed is replaced."""
        thumb = self.thumbnail(keyframe)
        row = self._row_of.get(keyframe.id)
        if row is None:
            row = len(self._row_of)
            self._grow(row + 1)
            self._row_of[keyframe.id] = row
            self._ids[row] = keyframe.id
        self._thumbs[row] = thumb
        self._sq_norms[row] = float(thumb @ thumb)

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        """Forget ``keyframe`` (swap-remove); unknown ids are ignored."""
        row = self._row_of.pop(keyframe.id, None)
        if row is None:
            return
        last = len(self._row_of)  # index of the last used row, now that one id is gone
        if row != last:
            moved = int(self._ids[last])
            self._thumbs[row] = self._thumbs[last]
            self._sq_norms[row] = self._sq_norms[last]
            self._ids[row] = moved
            self._row_of[moved] = row

    def train(self) -> None:
        """Re-index every keyframe of the map (also run at construction)."""
        self._row_of.clear()
        for keyframe in self.map.snapshot().keyframes.values():
            self.add_keyframe(keyframe)

    def find_places(self, query: Frame, k: int, *, allowed: set[int] | None = None
                    ) -> list[PlaceCandidate]:
        """Up to ``k`` keyframes by decreasing ``-SSD`` (restricted to ``allowed`` ids)."""
        thumb = self.thumbnail(query)
        n = len(self._row_of)
        scores = self._scores(thumb, n)
        ids = self._ids[:n].copy()
        if allowed is not None:
            scores[~np.isin(ids, np.fromiter(allowed, np.int64, len(allowed)))] = -np.inf
        return _best_candidates(ids, scores, k)

    def _scores(self, thumb: Thumbs, n: int) -> npt.NDArray[np.float32]:
        """(n,) ``-SSD`` of ``thumb`` against the first ``n`` rows, one matrix-vector product."""
        cross = self._thumbs[:n] @ thumb
        ssd = self._sq_norms[:n] + np.float32(thumb @ thumb) - 2.0 * cross
        return -np.maximum(ssd, 0.0, dtype=np.float32)

    def _grow(self, rows: int) -> None:
        """Double the capacity until ``rows`` fit (amortised O(1) appends)."""
        cap = len(self._ids)
        if rows <= cap:
            return
        new_cap = max(rows, 2 * cap)
        thumbs = np.zeros((new_cap, self._dim), np.float32)
        thumbs[:cap] = self._thumbs
        self._thumbs = thumbs
        self._sq_norms = np.concatenate([self._sq_norms, np.zeros(new_cap - cap, np.float32)])
        self._ids = np.concatenate([self._ids, np.zeros(new_cap - cap, np.int64)])


def _best_candidates(ids: npt.NDArray[np.int64], scores: npt.NDArray[np.floating], k: int
                     ) -> list[PlaceCandidate]:
    """The ``k`` best finite scores, best first (ties broken by keyframe id)."""
    order = top_k(scores, k, keep=np.isfinite(scores), tiebreak=ids)
    return [PlaceCandidate(int(ids[i]), float(scores[i])) for i in order]
