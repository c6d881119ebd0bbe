"""The engine shared by ``reloc eval`` and the service: the keyframe map, its builder and the
live relocalizers, safe for many querying threads and one mapping thread.

Concurrency
-----------
The engine holds the one lock discipline of the library. The map's writers, the place finders
(sbi, bow, gt), the ferns models, the pose finders and the relocalizers take no lock: they are
NOT thread-safe by themselves and must only be used through an engine (or by one thread).

- ``_writer`` (mutex) guards :attr:`Engine.map` and its builder: one map change at a time.
  Features and triangulation run under it alone, so queries go on meanwhile; readers of
  ``Engine.map`` need no lock (each :meth:`KeyframeMap.snapshot` is immutable).
- ``_rw`` (readers-writer, writers first) guards the live relocalizers, the map views they read
  through and the method table. Queries, :meth:`Engine.status` and :meth:`Engine.save` take the
  read side; publishing a map change (re-pinning the views, then each relocalizer's
  ``add_keyframe``/``remove_keyframe``) and swapping a new build in take the write side. A
  query thus sees one published map version, every relocalizer in step with it, throughout.
- A method's build lock lets one build of that method run at a time (:meth:`Engine.train`, a
  lazily created method); ``_meta`` guards the build bookkeeping (builds in flight, the
  journal of keyframes changed since they started); ``_save_lock`` serialises saves.
- Order, never reversed: build lock, ``_writer``, ``_rw``, ``_meta``; ``_save_lock``, ``_rw``.

Training never blocks queries: a fresh relocalizer is built off-lock over a pinned snapshot
(no other thread can see it), then, under the write side, the keyframes changed since are
replayed into it from the journal and it is swapped in.

What this asks of a relocalizer: ``add_keyframe``, ``remove_keyframe``, ``train`` and ``load``
run under the write side or before it is published; ``relocalize`` runs concurrently with
other queries on the same instance (the read side is shared), and ``save`` beside them, so
both only read its state or memoise a value every racing query would compute identically
(bow's inverted file, ferns' landmark table, the caches of the shared keyframes). A query
:class:`Frame` belongs to one query. :meth:`Engine.relocalizer` hands out a live relocalizer
without any lock: for single-threaded tools only.
"""

from __future__ import annotations

import functools
import logging
import os
import tempfile
import threading
import time
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy.typing as npt

from ..algorithms.pose.keyframe_disagreement import KeyframePoseSigma, keyframe_pose_sigma
from ..algorithms.pose.map_consistency import statistics_bytes
from ..algorithms.pose.map_pool import pool_bytes
from ..algorithms.relocalizers.base import Prior, Relocalizer, RelocResult
from ..algorithms.relocalizers.factory import create_relocalizer, create_tracker
from ..algorithms.relocalizers.map_pools import restore_pools, save_pools
from ..algorithms.relocalizers.map_statistics import restore_statistics, save_statistics
from ..algorithms.relocalizers.tracking_fallback import relocalize_with_prior
from ..core.background import LOWER_PRIORITY, lower_priority, start_background
from ..core.cameras import Camera
from ..core.foreground import answering
from ..core.frame import EncodedImage, Frame, Keyframe
from ..core.map import KeyframeMap, MapState
from ..core.map_view import MapView
from ..core.mapping import MapBuilder, MappingConf
from ..core.progress import progress as progress_bar
from ..core.read_write_lock import ReadWriteLock
from ..core.triangulation import TriangulationConf
from ..storage.keyframe_parts import StoredParts
from ..storage.snapshot import load_map, model_dir_name, save_map
from .conf import EngineConf

log = logging.getLogger(__name__)

#: Seconds a count of a map's statistics records stands (they are made when it trains or
#: loads, and for a keyframe added since at the first query near it).
STATISTICS_RECOUNT_S = 5.0

__all__ = ["Engine", "EngineConf", "MappingConf", "TriangulationConf"]

Array = npt.NDArray[Any]


@dataclass
class _Live:
    """A relocalizer in service and the view it reads the map through."""

    relocalizer: Relocalizer
    view: MapView
    #: Tracking from a prior with a covariance, asked before ``relocalizer`` when a query
    #: carries one (:mod:`..algorithms.relocalizers.tracking`), over the same view.
    tracker: Relocalizer | None = None


class Engine:
    """Map, builder and relocalizers behind one API (see module docstring)."""

    def __init__(self, conf: EngineConf | None = None) -> None:
        self.conf = conf or EngineConf()
        #: The map the builder writes (may be ahead of what relocalizers see: :meth:`status`);
        #: written only under ``_writer``, read by anyone through ``snapshot()``.
        self.map = KeyframeMap(default_pose_covariance=self.conf.mapping.default_pose_covariance(),
                               calibration_covariance=self.conf.mapping.calibration_covariance())
        self._rw = ReadWriteLock()                # relocalizers, their views, _live
        self._writer = threading.Lock()           # serialises map changes
        self._save_lock = threading.Lock()        # one save at a time
        self._method_locks: dict[str, threading.Lock] = {}  # one build per method at a time
        self._meta = threading.Lock()             # _method_locks, _building and _journal
        self._building: dict[str, int] = {}       # method -> base version of builds in flight
        self._journal: list[tuple[int, int]] = []  # (published version, keyframe id changed)
        self._published = self.map.snapshot()
        #: The keyframe pose uncertainty last measured from the map (``mapping`` sigmas
        #: ``"auto"``: at each :meth:`train` and :meth:`load`), its default pose covariance.
        self.keyframe_pose_sigma: KeyframePoseSigma | None = None
        self._live: dict[str, _Live] = {}
        #: Set once the pools a load prepares are made (:meth:`load`); set at once otherwise.
        self.prepared = threading.Event()
        self.prepared.set()
        #: The models directory :meth:`load` read and the state it made of it (while that
        #: state lives): a save of that very state carries its stored pool indexes over.
        self._loaded_from: tuple[Path, weakref.ref[MapState]] | None = None
        #: The relocalizers :meth:`load` restored, when it restored every method's model.
        self._loaded_live: list[weakref.ref[_Live]] | None = None
        #: Feature kinds whose pool index the load read rather than built (set with
        #: :attr:`prepared`); :meth:`close` stops the pools still to be made.
        self.pools_read: list[str] = []
        #: Feature kinds whose keyframe statistics the load read (:meth:`load`).
        self.statistics_read: list[str] = []
        self._closed = threading.Event()
        #: (state, when, bytes) of the last count of its keyframes' statistics records
        self._statistics_counted: tuple[weakref.ref[MapState], float, int] | None = None
        kinds: set[str] = set()
        for method in self.conf.methods:
            live = self._create(method, self._published)
            kinds |= live.relocalizer.required_features
            self._live[method] = live
        self.builder = MapBuilder(self.map, self.conf.mapping.with_kinds(sorted(kinds)))

    # -- map changes (write) -------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, image: npt.ArrayLike | EncodedImage, camera: Camera,
                     world_from_cam: Array,
                     *, depth: npt.ArrayLike | None = None, timestamp: float | None = None,
                     given_keypoints_px: npt.ArrayLike | None = None,
                     given_landmark_ids: npt.ArrayLike | None = None,
                     given_points_world: npt.ArrayLike | None = None,
                     pose_covariance: npt.ArrayLike | None = None) -> Keyframe:
        """Add (or replace) a posed keyframe: features and landmarks (see
        :meth:`MapBuilder.add_keyframe`), then every live relocalizer learns it.
        ``pose_covariance`` (6, 6): how well ``world_from_cam`` is known (None: the map's
        default, ``mapping.keyframe_position_sigma_m`` and ``..._rotation_sigma_deg``)."""
        with self._writer:
            old = self.map.snapshot().keyframes.get(kf_id)
            keyframe = self.builder.add_keyframe(
                kf_id, image, camera, world_from_cam, depth=depth, timestamp=timestamp,
                given_keypoints_px=given_keypoints_px, given_landmark_ids=given_landmark_ids,
                given_points_world=given_points_world, pose_covariance=pose_covariance)
            with self._rw.write():
                self._publish([kf_id])
                for live in self._live.values():
                    if old is not None:
                        live.relocalizer.remove_keyframe(old)
                    live.relocalizer.add_keyframe(keyframe)
        return keyframe

    def remove_keyframe(self, kf_id: int) -> Keyframe:
        """Remove keyframe ``kf_id`` from the map and every relocalizer; MapError if unknown."""
        with self._writer:
            keyframe = self.builder.remove_keyframe(kf_id)
            with self._rw.write():
                self._publish([kf_id])
                for live in self._live.values():
                    live.relocalizer.remove_keyframe(keyframe)
        return keyframe

    def _publish(self, changed: Sequence[int]) -> None:
        """Under the write lock: show the builder's map to every relocalizer; journal the
        keyframes ``changed`` for builds in flight."""
        self._published = self.map.snapshot()
        for live in self._live.values():
            live.view.pin(self._published)
        with self._meta:
            if self._building:
                self._journal.extend((self._published.version, k) for k in changed)
            else:
                self._journal.clear()

    # -- queries (read) ------------------------------------------------------------------------
    def relocalize(self, query: Frame, *, method: str | None = None, prior: Prior | None = None,
                   hypotheses: int = 1) -> RelocResult:
        """The query's pose by ``method`` (default: the first configured). A method not yet
        built is created, fed every keyframe and trained first (blocking this caller only)."""
        method = (method or self.conf.default_method).strip()
        start = time.perf_counter()
        build = 0.0
        if method not in self._live:
            self._build_and_swap(method, progress=False, only_if_missing=True)
            build = time.perf_counter() - start
        wait_start = time.perf_counter()
        with self._rw.read(), answering():
            waited = time.perf_counter() - wait_start
            live = self._live[method]
            version = live.view.version
            result = relocalize_with_prior(live.relocalizer, live.tracker, query, prior=prior,
                                           hypotheses=hypotheses)
        result.map_version = version
        result.timings["engine_wait"] = waited
        if build:
            result.timings["engine_build"] = build
        result.timings["engine_total"] = time.perf_counter() - start
        return result

    def status(self) -> dict[str, Any]:
        """Keyframes, landmarks and version of the published map; each method's state."""
        with self._rw.read():
            state = self._published
            methods = {m: {"trained": bool(live.relocalizer.trained),
                           "default": m == self.conf.default_method,
                           "map_version": live.view.version}
                       for m, live in self._live.items()}
        with self._meta:
            building = sorted(self._building)
        return {"keyframes": len(state.keyframes), "landmarks": len(state.landmarks),
                "map_version": state.version, "default_method": self.conf.default_method,
                "methods": methods, "building": building,
                "keyframe_pose_sigma": (None if self.keyframe_pose_sigma is None
                                        else self.keyframe_pose_sigma.as_dict()),
                "feature_kinds": list(self.builder.conf.feature_kinds)}

    @property
    def methods(self) -> list[str]:
        """Methods with a live relocalizer."""
        return list(self._live)

    def relocalizer(self, method: str) -> Relocalizer | None:
        """The live relocalizer answering ``method`` (None if not built yet). Calling it
        bypasses the engine's locks: only where no other thread uses the engine."""
        live = self._live.get(method)
        return None if live is None else live.relocalizer

    # -- training (off-lock build, then swap) --------------------------------------------------
    def train(self, methods: Sequence[str] | None = None, *, progress: bool = False) -> None:
        """(Re)build and train ``methods`` (default: every live one) from the current map
        without blocking queries; each is swapped in when ready."""
        if self._measures_keyframe_sigma(self._published):
            measured = keyframe_pose_sigma(self._published)
            with self._writer, self._rw.write():
                self._set_keyframe_sigma(measured)
                self._publish([])
        for method in (methods if methods is not None else list(self._live)):
            self._build_and_swap(method.strip(), progress=progress, only_if_missing=False)

    def _measures_keyframe_sigma(self, state: MapState) -> bool:
        """Whether the map measures its keyframes' pose uncertainty: the mapping sigmas are
        ``"auto"`` and some keyframe of ``state`` was put without a covariance."""
        return self.conf.mapping.keyframe_sigma_auto and any(
            kf.pose_covariance is None for kf in state.keyframes.values())

    def _set_keyframe_sigma(self, measured: KeyframePoseSigma | None) -> None:
        """Under the writer lock: ``measured`` (None: too few keyframes to tell, taken as
        exact) becomes the map's default keyframe pose covariance."""
        self.keyframe_pose_sigma = measured
        self.map.set_default_pose_covariance(None if measured is None else measured.covariance())

    def _method_lock(self, method: str) -> threading.Lock:
        with self._meta:
            return self._method_locks.setdefault(method, threading.Lock())

    def _create(self, method: str, state: MapState) -> _Live:
        view = MapView(state)
        relocalizer = create_relocalizer(method, view, options=self.conf.options)
        return _Live(relocalizer, view, create_tracker(view, options=self.conf.options))

    def _build_and_swap(self, method: str, *, progress: bool, only_if_missing: bool) -> None:
        with self._method_lock(method):
            if only_if_missing and method in self._live:
                return
            fresh = self._create(method, MapState())
            self._ensure_kinds(fresh.relocalizer.required_features)
            base = self._register_build(method)
            try:
                fresh.view.pin(base)
                self._feed(fresh.relocalizer, base, progress=progress, desc=f"{method}: keyframes")
                fresh.relocalizer.train(progress=progress)
                with self._rw.write():
                    self._replay(fresh, base)
                    self._live[method] = fresh
            finally:
                with self._meta:
                    self._building.pop(method, None)

    def _register_build(self, method: str) -> MapState:
        """The published state a build starts from, with journaling switched on for it."""
        with self._rw.read(), self._meta:
            self._building[method] = self._published.version
            return self._published

    @staticmethod
    def _feed(relocalizer: Relocalizer, state: MapState, *, progress: bool, desc: str) -> None:
        ids = state.keyframe_ids()
        for kf_id in (progress_bar(ids, desc=desc) if progress else ids):
            relocalizer.add_keyframe(state.keyframes[kf_id])

    def _replay(self, fresh: _Live, base: MapState) -> None:
        """Under the write lock: bring a relocalizer built on ``base`` up to the published
        state by replaying the keyframes changed since."""
        current = self._published
        with self._meta:
            changed = list(dict.fromkeys(k for v, k in self._journal if v > base.version))
        fresh.view.pin(current)
        for kf_id in changed:
            if kf_id in base.keyframes:
                fresh.relocalizer.remove_keyframe(base.keyframes[kf_id])
            if kf_id in current.keyframes:
                fresh.relocalizer.add_keyframe(current.keyframes[kf_id])

    def _ensure_kinds(self, kinds: frozenset[str]) -> None:
        """Extract feature kinds a new method needs and the map lacks (a write, rare)."""
        if set(kinds) <= set(self.builder.conf.feature_kinds):
            return
        with self._writer:
            updated = self.builder.add_feature_kinds(sorted(kinds))
            with self._rw.write():
                self._publish(updated)

    # -- persistence ---------------------------------------------------------------------------
    def save(self, directory: str | Path, *, exact_geometry: bool = False,
             store: Mapping[str, Any] | None = None, parts: StoredParts | None = None) -> Path:
        """Save the published map and every live relocalizer's models (consistent with it),
        with the whole-map pools' indexes and the keyframe statistics they hold
        (:mod:`..algorithms.relocalizers.map_pools`,
        :mod:`..algorithms.relocalizers.map_statistics`); returns the snapshot. Queries go
        on meanwhile: the read lock is held only while the relocalizers write their models
        (into a scratch directory), not for the map files.
        ``exact_geometry``: landmark geometry float64 as held; ``store``: the owner's fields
        of the manifest (see :func:`..storage.snapshot.save_map`); ``parts``: what is stored
        of each keyframe's depth and image (default: ``conf.stored``; images when it says
        ``"always"`` or a live relocalizer reads them)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        parts = parts or self.conf.stored
        with self._save_lock, tempfile.TemporaryDirectory(dir=directory, prefix=".models-") as tmp:
            with self._rw.read():
                state = self._published
                for method, live in self._live.items():
                    (Path(tmp) / model_dir_name(method)).mkdir()
                    live.relocalizer.save(Path(tmp) / model_dir_name(method),
                                          centres=parts.vocabulary)
                    save_pools(live.relocalizer, Path(tmp) / model_dir_name(method), state,
                               self._loaded_models(method, state))
                    save_statistics(live.relocalizer, Path(tmp) / model_dir_name(method), state)
                methods = list(self._live)
                reads_images = any(live.relocalizer.reads_keyframe_images
                                   for live in self._live.values())
                # every keypoint is kept while a method may read more than the landmark ones:
                # at a query, or at the training a load gives a method that saved no model
                every_row = any(live.relocalizer.reads_unmapped_keypoints
                                or not live.relocalizer.trained for live in self._live.values())
            parts = replace(parts, images="always" if parts.keeps_images(reads_images)
                            else "needed", descriptors="all" if every_row else parts.descriptors)
            models = {m: functools.partial(_move_contents, Path(tmp) / model_dir_name(m))
                      for m in methods}
            return save_map(state, directory, models=models, exact_geometry=exact_geometry,
                            store=store, parts=parts)

    @classmethod
    def load(cls, directory: str | Path, conf: EngineConf | None = None, *,
             progress: bool = False, train: bool = True, pools: bool = True) -> Engine:
        """An engine over the map saved in ``directory``. A method with saved models is
        created over the loaded map and restores them (nothing is re-added or retrained);
        one without is fed every keyframe and trained (with ``train`` False it stays
        untrained, as in the engine saved: a replica of it). ``pools``: make the whole-map
        pools its queries read on a thread of their own (:meth:`_start_prepare`); False for
        an engine that answers no query. The keyframe statistics stored with each method's
        model are given back to the map's keyframes
        (:func:`..algorithms.relocalizers.map_statistics.restore_statistics`): its first
        queries compute only those of keyframes whose inputs differ from those they were
        computed from."""
        state, models_dir = load_map(directory)
        engine = cls(conf)
        engine.map.replace_state(state)
        if engine._measures_keyframe_sigma(state):
            engine._set_keyframe_sigma(keyframe_pose_sigma(engine.map.snapshot()))
        engine.builder.add_feature_kinds(engine.builder.conf.feature_kinds)
        with engine._rw.write():
            engine._publish([])
        restored_all = True
        for method, live in list(engine._live.items()):
            path = models_dir / model_dir_name(method) if models_dir is not None else None
            if path is not None and path.is_dir():   # before training, which reads them
                engine.statistics_read += restore_statistics(live.relocalizer,
                                                             engine._published, path)
                restored = engine._create(method, engine._published)
                if restored.relocalizer.load(path):
                    engine._live[method] = restored
                    continue
            restored_all = False
            if pools and path is not None:   # before training, which would build them again
                engine.pools_read += restore_pools(live.relocalizer, engine._published, path)
            engine._feed(live.relocalizer, engine._published, progress=progress,
                         desc=f"{method}: keyframes")
            if train:
                live.relocalizer.train(progress=progress)
        if pools:
            engine._start_prepare(models_dir)
        if models_dir is not None:
            engine._loaded_from = (models_dir, weakref.ref(engine._published))
            if restored_all:
                engine._loaded_live = [weakref.ref(live) for live in engine._live.values()]
        return engine

    def loaded_snapshot(self) -> Path | None:
        """The snapshot directory :meth:`load` read, while this engine holds just what it
        holds: the map is the state made of it and every method is the model restored from
        it (none trained since, none added); else None."""
        loaded, live = self._loaded_from, self._loaded_live
        if loaded is None or live is None or loaded[1]() is not self._published:
            return None
        current = list(self._live.values())
        if len(current) != len(live) or any(r() is not c for r, c in zip(live, current,
                                                                         strict=True)):
            return None
        return loaded[0].parent

    def _loaded_models(self, method: str, state: MapState) -> Path | None:
        """The model directory of ``method`` that :meth:`load` read, if ``state`` is the
        state it made of it (unchanged since), else None."""
        loaded = self._loaded_from
        if loaded is None or loaded[1]() is not state:
            return None
        return loaded[0] / model_dir_name(method)

    def _start_prepare(self, models_dir: Path | None) -> None:
        """Make the whole-map pools the queries read
        (:func:`..algorithms.relocalizers.map_pools.restore_pools`) on a thread of their own,
        so that loading returns at once; a query that needs a pool still being made waits
        for it (:attr:`prepared` is set when all are made). The first method's first pool,
        which its first step reads (any query waits for it), is made at the queries'
        priority, the others below it: made below it too, it delayed a cold load's first
        answer while the warm-up or other maps' queries ran. The others also step aside
        while queries begun after them are answered (:mod:`..core.foreground`): made
        beside them, they slowed the queries just after a cold load."""
        with self._rw.read():
            work = [(live.relocalizer, None if models_dir is None
                     else models_dir / model_dir_name(m)) for m, live in self._live.items()]
            state = self._published
        self.prepared.clear()

        def run() -> None:
            try:
                if work:
                    self.pools_read += restore_pools(work[0][0], state, work[0][1],
                                                     self._closed.is_set, first=True)
                lower_priority(LOWER_PRIORITY)
                for relocalizer, directory in work:
                    self.pools_read += restore_pools(relocalizer, state, directory,
                                                     self._closed.is_set, step_aside=True)
            except Exception as exc:   # the first query makes what is missing
                log.error("preparing the map's pools failed: %s", exc)
            finally:
                self.prepared.set()

        # ended before the interpreter
        start_background(run, "map-pools", self._closed)

    def held_bytes(self) -> int:
        """Bytes the relocalizers hold for the published map beside it: its whole-map
        landmark pools and their indexes (:mod:`..algorithms.pose.map_pool`) and its
        keyframes' statistics (:mod:`..algorithms.pose.map_consistency`). Read without the
        engine's lock (the budget's count, called under other locks)."""
        state = self._published
        return pool_bytes(state) + self._statistics_bytes(state)

    def _statistics_bytes(self, state: MapState) -> int:
        """:func:`statistics_bytes` of ``state``, counted again at most every
        :data:`STATISTICS_RECOUNT_S` (a pass over its keyframes, which the budget's count
        would otherwise make several times after every query)."""
        counted = self._statistics_counted
        now = time.monotonic()
        if counted is None or counted[0]() is not state or now - counted[1] > STATISTICS_RECOUNT_S:
            counted = (weakref.ref(state), now, statistics_bytes(state))
            self._statistics_counted = counted
        return counted[2]

    def close(self) -> None:
        """Stop making the pools a load prepares, in the middle of one too (between its
        keyframes and its index's chunks; what was made of it is dropped): the map is
        closed, its memory goes with the last reference, not after a build nobody will
        read."""
        self._closed.set()


def _move_contents(source: Path, target: Path) -> None:
    """Move everything in ``source`` into the existing directory ``target`` (same file system)."""
    for child in source.iterdir():
        os.replace(child, target / child.name)
