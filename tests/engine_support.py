"""Helpers shared by the engine-level tests (not a test module): an engine over a synthetic
scene's keyframes, trained and saved, as the tests of what a save carries start from."""

from __future__ import annotations

from pathlib import Path

from reloc_service.engine import Engine, EngineConf


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
