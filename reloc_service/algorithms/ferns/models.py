"""The ferns relocalizer's models: one classifier per region of the map and the exact record of
what each learned (thesis 3.2, 5.2.2).

Every trained observation ``(keyframe, keypoint, landmark)`` is recorded; its samples are a
function of the keyframe image and ``(seed, keyframe id, warp)`` only
(:mod:`.training`), so an observation that leaves the map (its keyframe removed or replaced,
its landmark gone or changed) subtracts exactly what it added. At most ``max_classes``
landmarks per model: the most observed ones in one model (``partition = "select"``) or one
model per region (``"regions"``: k-means of keyframe positions, each landmark learned by the
region that observes it most and still has room).

:class:`FernModels` trains, updates and saves; queries read only :attr:`FernModels.published`
(:class:`Published`, replaced whole after every change).
"""

from __future__ import annotations

import math
import zlib
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.errors import StorageError
from ...core.frame import Keyframe
from ...core.map import MapState
from ...core.progress import progress
from .classifier import FernClassifier
from .fern_tests import FernConf, FernTests
from .scorer import FernScorer
from .training import WarpConf, draw_warps, sample_leaves

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class ModelsConf:
    """What training needs of the ferns relocalizer's options: the feature ``kind`` whose
    landmarks are learned, ``partition`` ("select" or "regions"), ``max_classes`` per model,
    ``num_warps`` samples per observation warped by ``workers`` threads, the classifier's and
    the warps' settings, and the k-means ``seed``."""

    kind: str
    partition: str
    max_classes: int
    num_warps: int
    workers: int
    fern: FernConf
    warp: WarpConf
    seed: int


@dataclass(frozen=True, eq=False)
class Observations:
    """Trained (or to be trained) observations of one keyframe: keypoint indices (n,) into
    ``keyframe.features[kind]`` and their landmark ids (n,)."""

    keyframe: Keyframe
    kp_idx: IntArray
    landmark_ids: IntArray

    def subset(self, mask: npt.NDArray[np.bool_]) -> Observations:
        return Observations(self.keyframe, self.kp_idx[mask], self.landmark_ids[mask])

    def landmark_at(self, num_keypoints: int) -> IntArray:
        """(num_keypoints,) landmark id of each keypoint, -1 where none is recorded."""
        out = np.full(num_keypoints, -1, np.int64)
        out[self.kp_idx] = self.landmark_ids
        return out


@dataclass(eq=False)
class Region:
    """One model: its classifier, the keyframes of its region and their mean position."""

    classifier: FernClassifier
    keyframe_ids: set[int]
    centre_world: Array


@dataclass(frozen=True, eq=False)
class Published:
    """What queries read, swapped atomically after each update: one scorer per region, the
    keyframes of each region and, per keyframe, the fraction of its trained landmarks each
    region learned ((R,) summing to 1)."""

    scorers: tuple[FernScorer, ...]
    region_keyframes: tuple[frozenset[int], ...]
    landmark_regions: Mapping[int, Array] = field(default_factory=dict)


class FernModels:
    """The region models, which landmark each learns, and the record of every trained
    observation. Not thread-safe: train, update and restore run behind the engine's write
    lock (or off-line); queries read :attr:`published` only."""

    def __init__(self, conf: ModelsConf, tests: FernTests) -> None:
        self.conf = conf
        self.tests = tests
        self._regions: list[Region] = []
        self._assign: dict[int, int] = {}          # landmark id -> region index
        self._lm_trained: Counter[int] = Counter()  # landmark id -> trained observations
        self._kf_region: dict[int, int] = {}
        self._trained: dict[int, Observations] = {}
        self.published = Published((), (), {})

    # -- what they hold ----------------------------------------------------------------------
    @property
    def classifiers(self) -> tuple[FernClassifier, ...]:
        return tuple(r.classifier for r in self._regions)

    def nbytes(self) -> int:
        """Bytes held by the classifiers (sparse counts, classes, tests)."""
        return sum(r.classifier.nbytes() for r in self._regions)

    def trained_observations(self) -> set[tuple[int, int, int]]:
        """Every trained ``(landmark id, keyframe id, keypoint index)``."""
        return {(int(lm), kf_id, int(i)) for kf_id, obs in self._trained.items()
                for i, lm in zip(obs.kp_idx, obs.landmark_ids, strict=True)}

    # -- training ----------------------------------------------------------------------------
    def train(self, state: MapState, *, show_progress: bool = False) -> None:
        """Partition ``state`` into regions (models start empty) and train every observation."""
        if self._regions or self._trained:
            raise RuntimeError("FernModels.train: these models are trained already; train a "
                               "new FernModels instead")
        self._partition(state)
        self.update(state, show_progress=show_progress)

    def update(self, state: MapState, *, show_progress: bool = False) -> None:
        """Subtract trained observations that left ``state``, train the new ones, publish."""
        current = current_observations(state, self.conf.kind)
        removals: list[Observations] = []
        additions: list[Observations] = []
        for kf_id in sorted(set(self._trained) | set(current)):
            removed, added = self._diff(self._trained.get(kf_id), current.get(kf_id))
            removals += removed
            additions += added
        self._apply(removals, -1, show_progress)
        self._release(removals)
        additions = [obs.subset(self._assignable(obs)) for obs in additions]
        self._apply([a for a in additions if len(a.kp_idx)], +1, show_progress)
        self._record(additions)
        self._publish()

    def _new_region(self, keyframe_ids: Iterable[int], centre_world: Array) -> int:
        self._regions.append(Region(FernClassifier(self.conf.fern), set(keyframe_ids),
                                    np.asarray(centre_world, np.float64)))
        return len(self._regions) - 1

    def _partition(self, state: MapState) -> None:
        """Regions and the landmarks each learns (thesis 5.2.2's scaling problem)."""
        current = current_observations(state, self.conf.kind)
        kf_ids = sorted(current)
        lms = _concat([current[k].landmark_ids for k in kf_ids])
        obs_kf = _concat([np.full(len(current[k].kp_idx), k) for k in kf_ids])
        num_landmarks = len(np.unique(lms))
        num_regions = 1
        if self.conf.partition == "regions" and kf_ids:
            num_regions = min(len(kf_ids), max(1, math.ceil(num_landmarks / self.conf.max_classes)))
        if not kf_ids:
            self._new_region([], np.zeros(3))
            return
        positions = state.positions_world(kf_ids)
        labels = kmeans_labels(positions, num_regions, self.conf.seed)
        num_regions = int(labels.max()) + 1
        for r in range(num_regions):
            members = [k for k, lab in zip(kf_ids, labels, strict=True) if lab == r]
            self._new_region(members, positions[labels == r].mean(0))
            self._kf_region.update({k: r for k in members})
        region_of_obs = labels[np.searchsorted(kf_ids, obs_kf)]
        self._assign = assign_landmarks(lms, region_of_obs, num_regions, self.conf.max_classes)

    def _region_for_keyframe(self, keyframe: Keyframe) -> int:
        """Region of a keyframe: known, else the nearest region centre (a new one if none)."""
        if keyframe.id in self._kf_region:
            return self._kf_region[keyframe.id]
        if not self._regions:
            self._new_region([], keyframe.position_world)
        centres = np.stack([r.centre_world for r in self._regions])
        r = int(np.argmin(np.linalg.norm(centres - keyframe.position_world, axis=1)))
        self._kf_region[keyframe.id] = r
        self._regions[r].keyframe_ids.add(keyframe.id)
        return r

    def _assignable(self, obs: Observations) -> npt.NDArray[np.bool_]:
        """Mask of observations whose landmark has (or now gets) a model with room."""
        region = self._region_for_keyframe(obs.keyframe)
        room = self.conf.max_classes - sum(1 for r in self._assign.values() if r == region)
        ok = np.zeros(len(obs.kp_idx), bool)
        for i, lm in enumerate(obs.landmark_ids.tolist()):  # per landmark, bookkeeping only
            if lm not in self._assign and room > 0:
                self._assign[lm] = region
                room -= 1
            ok[i] = lm in self._assign
        return ok

    def _diff(self, trained: Observations | None, cur: Observations | None
              ) -> tuple[list[Observations], list[Observations]]:
        """For one keyframe, the trained observations to subtract and the map's observations
        to add; drops the subtracted ones from the record."""
        removed = []
        # a new image object: a keyframe replaced (an unchanged one keeps its image object)
        replaced = cur is None or (trained is not None and cur.keyframe.image_source
                                   is not trained.keyframe.image_source)
        if trained is not None and replaced:
            removed.append(trained)  # keyframe removed, or replaced by another image
            del self._trained[trained.keyframe.id]
            trained = None
        if cur is None:
            return removed, []
        num_keypoints = len(cur.keyframe.features[self.conf.kind])
        now = cur.landmark_at(num_keypoints)
        if trained is not None:
            stale = now[trained.kp_idx] != trained.landmark_ids  # landmark gone or changed
            if stale.any():
                removed.append(trained.subset(stale))
                trained = self._trained[cur.keyframe.id] = trained.subset(~stale)
        before = (trained.landmark_at(num_keypoints) if trained is not None
                  else np.full(num_keypoints, -1, np.int64))
        fresh = cur.subset(now[cur.kp_idx] != before[cur.kp_idx])
        return removed, ([fresh] if len(fresh.kp_idx) else [])

    def _release(self, removed: list[Observations]) -> None:
        """Forget the landmarks left with no trained observation (frees their model's room)."""
        for obs in removed:
            self._lm_trained.subtract(obs.landmark_ids.tolist())
        for lm in [lm for lm, n in self._lm_trained.items() if n <= 0]:
            del self._lm_trained[lm]
            self._assign.pop(lm, None)

    def _record(self, added: list[Observations]) -> None:
        for obs in added:
            if not len(obs.kp_idx):
                continue
            self._lm_trained.update(obs.landmark_ids.tolist())
            old = self._trained.get(obs.keyframe.id)
            if old is None:
                self._trained[obs.keyframe.id] = obs
            else:
                self._trained[obs.keyframe.id] = Observations(
                    obs.keyframe, np.concatenate([old.kp_idx, obs.kp_idx]),
                    np.concatenate([old.landmark_ids, obs.landmark_ids]))

    def _apply(self, batches: list[Observations], sign: int, show_progress: bool) -> None:
        """Sample every batch (threads; a keyframe's warps split between them) and add or
        remove the samples."""
        if not batches:
            return
        chunks = np.array_split(np.arange(self.conf.num_warps), min(self.conf.workers,
                                                                    self.conf.num_warps))
        tasks = [(obs, chunk) for obs in batches for chunk in chunks]
        desc = "ferns: training" if sign > 0 else "ferns: forgetting"
        with ThreadPoolExecutor(max_workers=self.conf.workers) as pool:
            results = _bounded_map(pool, self._samples, tasks, 2 * self.conf.workers)
            if show_progress:
                results = progress(results, total=len(tasks), desc=desc)
            for (obs, _), leaves in zip(tasks, results, strict=True):
                self._count(obs, leaves, sign)

    def _samples(self, task: tuple[Observations, IntArray]) -> npt.NDArray[np.uint16]:
        """(w, n, M) leaves of the warped views ``task[1]`` of ``task[0]`` (a worker thread)."""
        obs, warp_indices = task
        feats = obs.keyframe.features[self.conf.kind]
        warps = draw_warps(self.conf.warp, obs.keyframe.id).take(warp_indices)
        return sample_leaves(self.tests, obs.keyframe.image, feats.keypoints_px[obs.kp_idx],
                             warps, self.conf.warp)

    def _count(self, obs: Observations, leaves: npt.NDArray[np.uint16], sign: int) -> None:
        regions = np.fromiter((self._assign[lm] for lm in obs.landmark_ids.tolist()), np.int64,
                              len(obs.landmark_ids))
        num_warps = leaves.shape[0]
        for r in np.unique(regions).tolist():
            sel = regions == r
            lv = leaves[:, sel].reshape(-1, leaves.shape[2])
            labels = np.tile(obs.landmark_ids[sel], num_warps)
            clf = self._regions[r].classifier
            (clf.add if sign > 0 else clf.remove)(lv, labels)

    def _publish(self) -> None:
        num = len(self._regions)
        ids = np.fromiter(self._assign.keys(), np.int64, len(self._assign))
        regs = np.fromiter(self._assign.values(), np.int64, len(self._assign))
        order = np.argsort(ids)
        ids, regs = ids[order], regs[order]
        votes = {}
        for kf_id, obs in self._trained.items() if len(ids) else ():  # numpy per keyframe
            pos = np.minimum(np.searchsorted(ids, obs.landmark_ids), len(ids) - 1)
            regions = regs[pos[ids[pos] == obs.landmark_ids]]
            if len(regions):
                votes[kf_id] = np.bincount(regions, minlength=num) / len(regions)
        self.published = Published(
            tuple(r.classifier.scorer() for r in self._regions),
            tuple(frozenset(r.keyframe_ids) for r in self._regions), votes)

    # -- persistence -------------------------------------------------------------------------
    def to_files(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """The arrays (counts per region, trained records, landmark assignment) and the JSON
        fields (regions, keyframe regions, each trained keyframe image's CRC-32) that
        :meth:`from_files` restores."""
        arrays: dict[str, Any] = {}
        for i, region in enumerate(self._regions):
            arrays.update({f"r{i}_{k}": v for k, v in region.classifier.to_arrays().items()})
        kf_ids = sorted(self._trained)
        arrays["obs_keyframe"] = _concat([np.full(len(self._trained[k].kp_idx), k)
                                          for k in kf_ids])
        arrays["obs_keypoint"] = _concat([self._trained[k].kp_idx for k in kf_ids])
        arrays["obs_landmark"] = _concat([self._trained[k].landmark_ids for k in kf_ids])
        n = len(self._assign)
        arrays["assign_landmark"] = np.fromiter(self._assign.keys(), np.int64, n)
        arrays["assign_region"] = np.fromiter(self._assign.values(), np.int64, n)
        meta = {"regions": [{"keyframe_ids": sorted(r.keyframe_ids),
                             "centre_world": r.centre_world.tolist()} for r in self._regions],
                "keyframe_region": {str(k): v for k, v in self._kf_region.items()},
                "keyframe_crc32": {str(k): image_crc(self._trained[k].keyframe)
                                   for k in kf_ids}}
        return arrays, meta

    @classmethod
    def from_files(cls, conf: ModelsConf, tests: FernTests, state: MapState,
                   arrays: Mapping[str, npt.NDArray[Any]], meta: Mapping[str, Any], *,
                   where: str) -> FernModels | None:
        """Models restored from :meth:`to_files`'s output over the map ``state``; None if a
        trained keyframe is missing from it or its image or keypoints changed since.
        StorageError naming ``where`` if the arrays are damaged."""
        trained = restore_records(state, conf.kind, arrays, meta["keyframe_crc32"])
        if trained is None:
            return None
        try:
            regions = [Region(FernClassifier.from_arrays(
                conf.fern, {k[len(f"r{i}_"):]: v for k, v in arrays.items()
                            if k.startswith(f"r{i}_")}),
                set(r["keyframe_ids"]), np.asarray(r["centre_world"], np.float64))
                for i, r in enumerate(meta["regions"])]
        except (KeyError, ValueError) as exc:
            raise StorageError(f"{where}: damaged ferns model ({exc})") from exc
        models = cls(conf, tests)
        models._regions, models._trained = regions, trained
        models._assign = dict(zip(arrays["assign_landmark"].tolist(),
                                  arrays["assign_region"].tolist(), strict=True))
        models._lm_trained = Counter(arrays["obs_landmark"].tolist())
        models._kf_region = {int(k): int(v) for k, v in meta["keyframe_region"].items()}
        models._publish()
        return models


# -- helpers -----------------------------------------------------------------------------------
def current_observations(state: MapState, kind: str) -> dict[int, Observations]:
    """Per keyframe, its keypoints of ``kind`` observing a landmark of ``state``."""
    live = np.fromiter(state.landmarks.keys(), np.int64, len(state.landmarks))
    out = {}
    for kf_id, kf in state.keyframes.items():
        feats = kf.features.get(kind)
        if feats is None or not len(feats):
            continue
        idx = np.flatnonzero((feats.landmark_ids >= 0) & np.isin(feats.landmark_ids, live))
        if len(idx):
            out[kf_id] = Observations(kf, idx.astype(np.int64), feats.landmark_ids[idx].copy())
    return out


def kmeans_labels(positions: Array, k: int, seed: int) -> IntArray:
    """Region label of each keyframe position (k-means, seeded); all 0 when k == 1."""
    if k <= 1 or len(positions) <= 1:
        return np.zeros(len(positions), np.int64)
    from scipy.cluster.vq import kmeans2

    _, labels = kmeans2(positions, k, seed=np.random.default_rng(seed), minit="++")
    # Renumber the non-empty clusters 0..k'-1.
    return np.unique(labels, return_inverse=True)[1].astype(np.int64)


def assign_landmarks(landmarks: IntArray, region_of_obs: IntArray, num_regions: int,
                     max_classes: int) -> dict[int, int]:
    """Each landmark to one region: the most observed landmarks first (the most distinctive:
    seen from most views; ties by id), each to the region that observes it most and still has
    room for ``max_classes`` classes; a landmark whose regions are all full is left out."""
    if len(landmarks) == 0:
        return {}
    pairs, votes = np.unique(np.column_stack([landmarks, region_of_obs]), axis=0,
                             return_counts=True)
    order = np.lexsort((pairs[:, 1], -votes, pairs[:, 0]))  # per landmark: most votes first
    pairs = pairs[order]
    ids, total = np.unique(landmarks, return_counts=True)
    starts = np.searchsorted(pairs[:, 0], ids)
    ends = np.r_[starts[1:], len(pairs)]
    room = np.full(num_regions, max_classes)
    out: dict[int, int] = {}
    for i in np.lexsort((ids, -total)).tolist():  # per landmark, at training time only
        for r in pairs[starts[i]:ends[i], 1].tolist():
            if room[r] > 0:
                out[int(ids[i])] = r
                room[r] -= 1
                break
    return out


def image_crc(keyframe: Keyframe) -> int:
    """CRC-32 of a keyframe's pixels: a saved model applies only to the images it learned."""
    return zlib.crc32(np.ascontiguousarray(keyframe.image).data)


def restore_records(state: MapState, kind: str, arrays: Mapping[str, npt.NDArray[Any]],
                    crcs: Mapping[str, int]) -> dict[int, Observations] | None:
    """Trained records rebound to the map's keyframes; None if a keyframe is missing or its
    image or keypoints changed since the model was saved."""
    kf, kp, lm = arrays["obs_keyframe"], arrays["obs_keypoint"], arrays["obs_landmark"]
    out = {}
    for kf_id in np.unique(kf).tolist():
        keyframe = state.keyframes.get(kf_id)
        if (keyframe is None or kind not in keyframe.features
                or image_crc(keyframe) != crcs.get(str(kf_id))):
            return None
        sel = kf == kf_id
        if kp[sel].max() >= len(keyframe.features[kind]):
            return None
        out[kf_id] = Observations(keyframe, kp[sel].astype(np.int64), lm[sel].astype(np.int64))
    return out


def _bounded_map(pool: ThreadPoolExecutor, fn: Any, items: list[Any], window: int
                 ) -> Iterator[Any]:
    """``pool.map(fn, items)`` in order, with at most ``window`` results waiting (memory)."""
    pending: deque[Future[Any]] = deque()
    for item in items:
        pending.append(pool.submit(fn, item))
        if len(pending) >= window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def _concat(parts: list[npt.NDArray[Any]]) -> IntArray:
    return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)
