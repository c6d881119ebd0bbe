"""A loaded map handed to a replica as the snapshot it was loaded from (hard links), only
while the engine holds just what that snapshot holds; else a save, as before."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from engine_support import saved_trained_engine

from reloc_service.core.frame import Frame
from reloc_service.core.mapping import MappingConf
from reloc_service.engine import Engine, EngineConf
from reloc_service.storage.snapshot import current_snapshot
from reloc_service.storage.snapshot_link import link_snapshot

METHOD = "sbi+p3p:orb,bow+p3p"   # bow has a trained model to save and restore


def conf() -> EngineConf:
    return EngineConf(methods=(METHOD,), mapping=MappingConf(max_features=400))


@pytest.fixture(scope="module")
def saved(synthetic_scene, tmp_path_factory) -> Path:
    return saved_trained_engine(synthetic_scene, conf(),
                                tmp_path_factory.mktemp("linked") / "map")[1]


def test_a_linked_snapshot_loads_as_the_original_without_a_copy(saved, synthetic_scene,
                                                                 tmp_path) -> None:
    snapshot = current_snapshot(saved)
    target = tmp_path / "base"
    target.mkdir()
    assert link_snapshot(snapshot, target)
    linked = current_snapshot(target)
    for path in snapshot.rglob("*"):
        if path.is_file():
            assert os.stat(path).st_ino == os.stat(linked / path.relative_to(snapshot)).st_ino
    a, b = Engine.load(saved, conf()), Engine.load(target, conf(), train=False)
    for image in synthetic_scene.query_images[:1]:
        ra = a.relocalize(Frame(image=image, camera=synthetic_scene.camera))
        rb = b.relocalize(Frame(image=image, camera=synthetic_scene.camera))
        assert (ra.ok, ra.reason) == (rb.ok, rb.reason)
        if ra.ok:
            np.testing.assert_array_equal(ra.world_from_cam, rb.world_from_cam)


def test_a_snapshot_gone_links_nothing(saved, tmp_path) -> None:
    copy = tmp_path / "map"
    shutil.copytree(saved, copy)
    snapshot = current_snapshot(copy)
    shutil.rmtree(snapshot)   # pruned meanwhile
    target = tmp_path / "base"
    target.mkdir()
    assert not link_snapshot(snapshot, target)
    assert list(target.iterdir()) == []


def test_an_engine_names_its_snapshot_only_while_it_holds_just_that(saved, synthetic_scene
                                                                    ) -> None:
    engine = Engine.load(saved, conf(), pools=False)
    assert engine.loaded_snapshot() == current_snapshot(saved)
    engine.train()   # new models, not the snapshot's
    assert engine.loaded_snapshot() is None

    engine = Engine.load(saved, conf(), pools=False)
    scene = synthetic_scene
    engine.add_keyframe(1000, scene.keyframe_images[0], scene.camera, scene.keyframe_poses[0])
    assert engine.loaded_snapshot() is None   # a map the snapshot does not hold


def test_an_engine_that_trained_a_method_at_load_names_no_snapshot(saved) -> None:
    two = EngineConf(methods=(METHOD, "sbi+p3p"), mapping=MappingConf(max_features=400))
    engine = Engine.load(saved, two, pools=False)   # sbi+p3p: no saved model, trained here
    assert engine.loaded_snapshot() is None


@pytest.mark.slow   # a service with a worker process: 10-20 s on a shared machine
def test_a_cold_loaded_map_reaches_the_workers_without_a_save(saved, synthetic_scene,
                                                              tmp_path, monkeypatch) -> None:
    """Worker processes, a stored map loaded on its first query: the workers load the
    snapshot it was loaded from (no save of the map on the way) and answer as it does."""
    from reloc_client.client import RelocClient
    from service_support import endpoint, free_port, service_conf

    from reloc_service.service.app import Service
    from reloc_service.tools.bench.stored_map import copy_map, stored_template

    scene = synthetic_scene
    template = stored_template(tmp_path / "template", "template", Engine.load(saved, conf()))
    copy_map(template, tmp_path / "storage", "alpha")
    saves: list[Path] = []
    real_save = Engine.save

    def save(self, directory, **kw):
        saves.append(Path(directory))
        return real_save(self, directory, **kw)

    monkeypatch.setattr(Engine, "save", save)
    port = free_port()
    service = Service(service_conf(port, tmp_path / "storage", methods=[METHOD],
                                   default_method=METHOD, worker_mode="process", workers=1,
                                   snapshot_every=0, max_resident_mb=100_000)).start()
    try:
        with RelocClient(endpoint(port), map="alpha", timeout=120) as client:
            answer = client.relocalize(scene.query_images[0], camera_id="cam0")
        assert not saves, f"the map was saved again for the workers: {saves}"
    finally:
        service.stop()
    local = Engine.load(template.directory / "map", conf()).relocalize(
        Frame(image=scene.query_images[0], camera=scene.camera))
    assert (answer.ok, local.ok) == (True, True)
    np.testing.assert_allclose(answer.world_from_cam, local.world_from_cam, atol=1e-12)
