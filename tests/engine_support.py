"""Helpers shared by the engine-level tests (not a test module): an engine over a synthetic
scene's keyframes, trained and saved, as the tests of what a save carries start from, and a count of the
repetition-index builds a load makes."""

from __future__ import annotations

import threading
from pathlib import Path

from reloc_service.algorithms.pose.repetition_index import RepetitionIndex
from reloc_service.core.frame import Frame
from reloc_service.core.mapping import MappingConf
from reloc_service.engine import Engine, EngineConf

#: Few features per keyframe: engine tests exercise the engine, not the features' accuracy.
FAST_MAPPING = MappingConf(max_features=400)


def add_keyframes(engine: Engine, scene, ids) -> None:
    """Keyframes ``ids`` of ``scene`` into ``engine``, at their poses, stamped by their id."""
    for i in ids:
        engine.add_keyframe(i, scene.keyframe_images[i], scene.camera, scene.keyframe_poses[i],
                            timestamp=float(i))


def query_frame(scene, i: int = 0) -> Frame:
    """Query ``i`` of ``scene`` as a frame of the scene's camera."""
    return Frame(scene.query_images[i], scene.camera)


def trained_engine(scene, conf: EngineConf) -> Engine:
    """An engine of ``conf`` holding every keyframe of ``scene`` at its pose, trained."""
    engine = Engine(conf)
    for i, image in enumerate(scene.keyframe_images):
        engine.add_keyframe(i, image, scene.camera, scene.keyframe_poses[i])
    engine.train()
    return engine


def saved_trained_engine(scene, conf: EngineConf, directory: Path) -> tuple[Engine, Path]:
    """:func:`trained_engine`, saved to ``directory`` (its map, models and indexes)."""
    engine = trained_engine(scene, conf)
    engine.save(directory)
    return engine, directory


def count_builds(monkeypatch) -> list[int]:
    """Record every repetition-index build from now on in the returned list: on this thread
    or on threads started from now on. An engine of an earlier test may still be making its
    pools on a thread of its own; its builds are not the ones a test asks about."""
    made: list[int] = []
    real = RepetitionIndex.build.__func__   # type: ignore[attr-defined]
    earlier = set(threading.enumerate()) - {threading.current_thread()}
    lock = threading.Lock()

    def build(cls, *args, **kw):
        if threading.current_thread() not in earlier:
            with lock:
                made.append(1)
        return real(cls, *args, **kw)

    monkeypatch.setattr(RepetitionIndex, "build", classmethod(build))
    return made
