"""The engine: relocalizers over the map, concurrency (queries while mapping), training that
swaps in without blocking queries, lazy methods, feature kinds, persistence."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from engine_support import FAST_MAPPING, add_keyframes, query_frame

from reloc_service.algorithms.relocalizers.base import (
    RELOCALIZERS,
    Prior,
    Relocalizer,
    RelocResult,
    RelocStatus,
)
from reloc_service.core.errors import ConfigError, MapError, NotTrainedError
from reloc_service.core.frame import Frame, Keyframe
from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.core.map_view import MapView
from reloc_service.core.methods import MethodStep
from reloc_service.core.read_write_lock import ReadWriteLock
from reloc_service.engine import Engine, EngineConf


class Probe(Relocalizer):
    """Test relocalizer: answers the pose of the keyframe with the most similar small blurry
    image, and refuses when its index disagrees with the map it reads (a consistency probe).
    Options (``options[spec]``): ``gated`` (train waits for :data:`TRAIN_GATE`), ``kinds``
    (required feature kinds)."""

    def __init__(self, kmap: KeyframeMap, spec: str, options: Mapping[str, Any]) -> None:
        super().__init__(kmap)
        self.spec = spec
        self.gated = bool(options.get("gated", False))
        self.kinds = frozenset(options.get("kinds", ()))
        self.index: dict[int, np.ndarray] = {}
        self._trained = False
        self.train_calls = 0
        self.loaded: list[int] | None = None

    @classmethod
    def from_options(cls, step: MethodStep, kmap: KeyframeMap,
                     options: Mapping[str, Mapping[str, Any]]) -> Probe:
        return cls(kmap, str(step), options.get(str(step), {}))

    @property
    def method(self) -> str:
        return self.spec

    @property
    def required_features(self) -> frozenset[str]:
        return self.kinds

    def add_keyframe(self, keyframe: Keyframe) -> None:
        assert keyframe.id in self.map, "add_keyframe before the map holds the keyframe"
        self.index[keyframe.id] = keyframe.small_blurry_image()

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        del self.index[keyframe.id]

    def train(self, *, progress: bool = False) -> None:
        if self.gated:
            assert TRAIN_GATE.wait(10), "the test never opened the training gate"
        self._trained = True
        self.train_calls += 1

    @property
    def trained(self) -> bool:
        return self._trained

    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        if not self._trained:
            raise NotTrainedError(f"{self.spec} needs train()")
        state = self.map.snapshot()
        ids, scores = [], []
        for kf_id, sbi in self.index.items():      # a concurrent add would break this loop
            time.sleep(0)
            ids.append(kf_id)
            scores.append(float(np.sum((sbi - query.small_blurry_image()) ** 2)))
        if set(ids) != set(state.keyframes):
            return RelocResult.failure(self.spec, f"index {sorted(ids)} != map "
                                       f"{state.keyframe_ids()}", map_version=state.version)
        if not ids:
            return RelocResult.failure(self.spec, "empty map", map_version=state.version)
        best = ids[int(np.argmin(scores))]
        return RelocResult(RelocStatus.OK, self.spec,
                           world_from_cam=state.keyframes[best].world_from_cam,
                           matched_keyframe_ids=sorted(ids), map_version=state.version,
                           timings={"place": 0.0})

    def save(self, directory: Path, *, centres: str = "float16") -> None:
        (directory / "probe.json").write_text(json.dumps(sorted(self.index)))

    def load(self, directory: Path) -> bool:
        path = directory / "probe.json"
        if not path.is_file():
            return False
        self.loaded = json.loads(path.read_text())
        for keyframe in self.map.snapshot().keyframes.values():  # not fed by Engine.load
            self.add_keyframe(keyframe)
        self._trained = True
        return True


for _name in ("probe", "probe_slow", "probe_orb"):
    if _name not in RELOCALIZERS:
        RELOCALIZERS.register(_name)(type(f"Probe_{_name}", (Probe,), {}))

#: Training of ``probe_slow`` waits until the test opens this gate.
TRAIN_GATE = threading.Event()
TRAIN_GATE.set()
OPTIONS = {"probe_slow": {"gated": True}, "probe_orb": {"kinds": ["orb"]}}
def _engine(methods=("probe",), **kw) -> Engine:
    return Engine(EngineConf(methods=methods, options=OPTIONS, mapping=FAST_MAPPING), **kw)


def test_engine_basics(synthetic_scene):
    engine = _engine()
    assert engine.status()["keyframes"] == 0
    add_keyframes(engine, synthetic_scene, range(3))
    with pytest.raises(NotTrainedError):
        engine.relocalize(query_frame(synthetic_scene))
    engine.train()
    result = engine.relocalize(query_frame(synthetic_scene))
    assert result.ok and result.matched_keyframe_ids == [0, 1, 2]
    assert result.map_version == engine.map.version
    assert {"engine_wait", "engine_total", "place"} <= set(result.timings)
    status = engine.status()
    assert status["keyframes"] == 3
    assert status["landmarks"] == len(engine.map.snapshot().landmarks) > 0
    assert status["map_version"] == engine.map.version and status["default_method"] == "probe"
    assert status["methods"] == {"probe": {"trained": True, "default": True,
                                           "map_version": engine.map.version}}
    removed = engine.remove_keyframe(1)
    assert removed.id == 1
    result = engine.relocalize(query_frame(synthetic_scene))
    assert result.ok and result.matched_keyframe_ids == [0, 2]
    with pytest.raises(MapError):
        engine.remove_keyframe(1)
    # Replacing a keyframe: the relocalizer forgets the old one and learns the new one.
    add_keyframes(engine, synthetic_scene, [2])
    assert engine.relocalize(query_frame(synthetic_scene)).matched_keyframe_ids == [0, 2]


def test_engine_conf_validation():
    with pytest.raises(ConfigError, match="methods"):
        EngineConf(methods=())
    with pytest.raises(ConfigError, match="unknown relocalizer"):
        Engine(EngineConf(methods=("no_such_method",)))
    conf = EngineConf(methods=["probe"], mapping={"neighbours": 2, "triangulation": {"ratio": 0.7}})
    assert conf.methods == ("probe",) and conf.mapping.neighbours == 2
    assert conf.mapping.triangulation.ratio == 0.7 and conf.default_method == "probe"


def test_feature_kinds_are_the_union_of_methods_and_mapping(synthetic_scene):
    engine = _engine(methods=("probe", "probe_orb"))
    assert engine.builder.conf.feature_kinds == ("sift", "orb")
    add_keyframes(engine, synthetic_scene, range(2))
    kf = engine.map.snapshot().keyframes[1]
    assert set(kf.features) == {"sift", "orb"}
    assert engine.map.snapshot().landmark_count("orb") > 0


def test_lazy_method_is_built_fed_and_trained(synthetic_scene):
    engine = _engine()
    add_keyframes(engine, synthetic_scene, range(3))
    engine.train()
    result = engine.relocalize(query_frame(synthetic_scene), method="probe_orb")
    assert result.ok and result.matched_keyframe_ids == [0, 1, 2]
    assert "engine_build" in result.timings
    assert engine.methods == ["probe", "probe_orb"]
    assert engine.relocalizer("probe_orb").train_calls == 1
    # It needed ORB: every keyframe got ORB features and landmarks.
    state = engine.map.snapshot()
    assert all("orb" in kf.features for kf in state.keyframes.values())
    assert state.landmark_count("orb") > 0
    again = engine.relocalize(query_frame(synthetic_scene), method="probe_orb")
    assert "engine_build" not in again.timings
    with pytest.raises(ConfigError):
        engine.relocalize(query_frame(synthetic_scene), method="nope")


def test_concurrent_queries_see_consistent_map_versions(synthetic_scene):
    """Threads relocalize non-stop while keyframes are added and removed: no exception, and
    every answer was computed on one published map version, whose keyframes the relocalizer
    had all learnt (the probe refuses otherwise)."""
    engine = _engine()
    add_keyframes(engine, synthetic_scene, [0])
    engine.train()
    published = {engine.map.version: [0]}
    stop = threading.Event()
    results: list[RelocResult] = []
    errors: list[BaseException] = []

    def query_loop(i: int) -> None:
        frame = query_frame(synthetic_scene, i % 3)
        try:
            while not stop.is_set():
                results.append(engine.relocalize(frame))
        except BaseException as exc:  # noqa: BLE001 - the test reports it
            errors.append(exc)

    threads = [threading.Thread(target=query_loop, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    try:
        for i in range(1, 6):
            add_keyframes(engine, synthetic_scene, [i])
            published[engine.map.version] = engine.map.snapshot().keyframe_ids()
            if i == 3:
                engine.remove_keyframe(1)
                published[engine.map.version] = engine.map.snapshot().keyframe_ids()
    finally:
        stop.set()
        for t in threads:
            t.join()
    assert not errors
    assert len(results) > 20
    assert all(r.ok for r in results), {r.reason for r in results if not r.ok}
    for r in results:
        assert r.map_version in published
        assert r.matched_keyframe_ids == published[r.map_version]
    assert len({r.map_version for r in results}) >= 3


def test_train_swaps_in_without_blocking_queries(synthetic_scene):
    engine = _engine(methods=("probe_slow",))
    add_keyframes(engine, synthetic_scene, range(2))
    engine.train()
    old = engine.relocalizer("probe_slow")
    TRAIN_GATE.clear()
    trainer = threading.Thread(target=engine.train)
    trainer.start()
    deadline = time.monotonic() + 5
    while engine.status()["building"] != ["probe_slow"] and time.monotonic() < deadline:
        time.sleep(0.005)
    assert engine.status()["building"] == ["probe_slow"]
    # While it trains: keyframes come and go, queries are answered by the old relocalizer.
    add_keyframes(engine, synthetic_scene, [2, 3])
    engine.remove_keyframe(0)
    try:
        result = engine.relocalize(query_frame(synthetic_scene))
        assert trainer.is_alive()
        assert result.ok and result.matched_keyframe_ids == [1, 2, 3]
        assert engine.relocalizer("probe_slow") is old
    finally:
        TRAIN_GATE.set()
    trainer.join()
    new = engine.relocalizer("probe_slow")
    assert new is not old and new.train_calls == 1
    assert sorted(new.index) == [1, 2, 3]              # replayed changes made during training
    result = engine.relocalize(query_frame(synthetic_scene))
    assert result.ok and result.matched_keyframe_ids == [1, 2, 3]
    assert engine.status()["building"] == []
    assert isinstance(new.map, MapView)
    with pytest.raises(MapError, match="read-only"):
        new.map.remove_keyframe(1)


def test_save_and_load(tmp_path, synthetic_scene):
    engine = _engine()
    add_keyframes(engine, synthetic_scene, range(3))
    engine.train()
    snapshot = engine.save(tmp_path / "map")
    assert (snapshot / "models" / "probe" / "probe.json").is_file()
    loaded = Engine.load(tmp_path / "map", EngineConf(methods=("probe", "probe_slow"), options={},
                                                      mapping=FAST_MAPPING))
    assert loaded.status()["keyframes"] == 3
    assert loaded.map.snapshot().landmarks.keys() == engine.map.snapshot().landmarks.keys()
    assert loaded.relocalizer("probe").loaded == [0, 1, 2]          # models restored
    assert loaded.relocalizer("probe").train_calls == 0
    assert loaded.relocalizer("probe_slow").train_calls == 1        # nothing saved: trained
    result = loaded.relocalize(query_frame(synthetic_scene))
    assert result.ok and result.matched_keyframe_ids == [0, 1, 2]
    assert result.map_version == engine.map.version


def test_read_write_lock_excludes_writers_and_prefers_them():
    lock = ReadWriteLock()
    log: list[str] = []
    reader_in = threading.Event()
    release_reader = threading.Event()

    def reader(name: str, hold: threading.Event | None) -> None:
        with lock.read():
            log.append(f"{name} in")
            if hold is not None:
                reader_in.set()
                hold.wait(2)
            log.append(f"{name} out")

    def writer() -> None:
        with lock.write():
            log.append("writer")

    first = threading.Thread(target=reader, args=("r1", release_reader))
    first.start()
    reader_in.wait(2)
    w = threading.Thread(target=writer)
    w.start()
    time.sleep(0.05)                       # the writer now waits for r1
    second = threading.Thread(target=reader, args=("r2", None))
    second.start()
    time.sleep(0.05)                       # r2 must queue behind the waiting writer
    assert log == ["r1 in"]
    release_reader.set()
    for t in (first, w, second):
        t.join(2)
    assert log == ["r1 in", "r1 out", "writer", "r2 in", "r2 out"]


def test_map_view_is_pinned():
    view = MapView()
    assert len(view) == 0 and view.version == 0
    state = MapState(version=7)
    view.pin(state)
    assert view.snapshot() is state and view.version == 7 and 3 not in view


def test_sbi_p3p_smoke(synthetic_scene):
    """The real default method, if its plugins are present: queries relocalize to mm."""
    pytest.importorskip("reloc_service.algorithms.relocalizers.multi")
    pytest.importorskip("reloc_service.algorithms.place.sbi")
    pytest.importorskip("reloc_service.algorithms.pose.p3p")
    from reloc_service.core.geometry import pose_error

    engine = Engine(EngineConf(methods=("sbi+p3p",)))
    add_keyframes(engine, synthetic_scene, range(6))
    engine.train()
    for image, pose in zip(synthetic_scene.query_images, synthetic_scene.query_poses, strict=True):
        result = engine.relocalize(Frame(image, synthetic_scene.camera))
        assert result.ok, result.reason
        dist, angle = pose_error(result.world_from_cam, pose)
        assert dist < 0.02 and np.degrees(angle) < 0.5


def test_answers_carry_the_keyframes_pose_covariance(synthetic_scene):
    """Keyframes put without a covariance take the map's default (5 cm, 1 deg here): every
    answer's position sigma is then at least about 5 cm, and the verification, which judges
    the pose against the map, accepts the same answers as with exact keyframes."""
    pytest.importorskip("reloc_service.algorithms.pose.p3p")
    from reloc_service.algorithms.relocalizers.base import position_sigma_m

    exact = Engine(EngineConf(methods=("sbi+p3p",), mapping={
        "keyframe_position_sigma_m": 0.0, "keyframe_rotation_sigma_deg": 0.0}))
    loose = Engine(EngineConf(methods=("sbi+p3p",), mapping={
        "keyframe_position_sigma_m": 0.05, "keyframe_rotation_sigma_deg": 1.0}))
    for engine in (exact, loose):
        add_keyframes(engine, synthetic_scene, range(6))
        engine.train()
    for image in synthetic_scene.query_images:
        a = exact.relocalize(Frame(image, synthetic_scene.camera))
        b = loose.relocalize(Frame(image, synthetic_scene.camera))
        assert a.ok and b.ok and np.allclose(a.world_from_cam, b.world_from_cam)
        assert position_sigma_m(a.covariance) < 0.045 < position_sigma_m(b.covariance)


def test_the_maps_calibration_accuracy_changes_the_stated_covariance_not_the_answer(
        synthetic_scene):
    """A map whose calibration is stated exact and one whose calibration is stated loose
    (``[mapping] calibration_*``) give every query the same answer (status, pose, inliers),
    the loose one with a wider covariance: the calibration's part of what the answer states,
    which no decision reads."""
    pytest.importorskip("reloc_service.algorithms.pose.p3p")
    from reloc_service.algorithms.relocalizers.base import position_sigma_m

    exact_kf = {"keyframe_position_sigma_m": 0.0, "keyframe_rotation_sigma_deg": 0.0}
    engines = [Engine(EngineConf(methods=("sbi+p3p",), mapping={
        **exact_kf, "calibration_focal_sigma_rel": focal, "calibration_radial_sigma_px": radial}))
        for focal, radial in ((0.0, 0.0), (0.02, 4.0))]
    for engine in engines:
        add_keyframes(engine, synthetic_scene, range(6))
        engine.train()
    wider = 0
    for image in synthetic_scene.query_images:
        a, b = (engine.relocalize(Frame(image, synthetic_scene.camera)) for engine in engines)
        assert a.ok and b.ok and (a.status, a.inliers, a.method) == (b.status, b.inliers, b.method)
        np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)
        assert a.covariance is not None and b.covariance is not None
        assert np.linalg.eigvalsh(b.covariance - a.covariance).min() > -1e-12
        wider += position_sigma_m(b.covariance) > 1.05 * position_sigma_m(a.covariance)
    assert wider >= 1
