"""The repetition check's whole-map pool at load: its index saved with the map's models and
read back (not trained again) by ``Engine.load``, built there when none fits, before any
query; a damaged stored index refused by name; the pool's bytes counted as the map's."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from engine_support import count_builds, saved_trained_engine

from reloc_service.algorithms.pose.map_consistency import statistics_bytes
from reloc_service.algorithms.pose.map_pool import held_pool
from reloc_service.algorithms.pose.repetition_index import IndexConf
from reloc_service.core.errors import StorageError
from reloc_service.core.mapping import MappingConf
from reloc_service.engine import Engine, EngineConf
from reloc_service.storage.snapshot import current_snapshot, model_dir_name

METHOD = "sbi+p3p:orb"


def conf(exact_rows: int) -> EngineConf:
    """Every pool above ``exact_rows`` rows is indexed (0: every pool of these small maps)."""
    return EngineConf(methods=(METHOD,), mapping=MappingConf(max_features=400),
                      options={"p3p": {"repetition_exact_rows": exact_rows}})


@pytest.fixture(scope="module")
def saved(synthetic_scene, tmp_path_factory) -> tuple[Engine, Path]:
    """An engine over the scene's keyframes, trained (its pool indexed), saved."""
    return saved_trained_engine(synthetic_scene, conf(0),
                                tmp_path_factory.mktemp("pool-store") / "map")


def stored_index(directory: Path) -> Path:
    return current_snapshot(directory) / "models" / model_dir_name(METHOD) / "repetition" / \
        "orb.leaves.npz"



def test_a_load_reads_the_stored_index_instead_of_building_it(saved, synthetic_scene,
                                                               monkeypatch) -> None:
    engine, directory = saved
    assert stored_index(directory).is_file()
    before = held_pool(engine.map.snapshot(), "orb", IndexConf(exact_rows=0))
    assert before is not None and before.index.tree is not None
    made = count_builds(monkeypatch)
    loaded = Engine.load(directory, conf(0))
    # A query at once waits for the pool being read rather than building one of its own.
    loaded.relocalize(_frame(synthetic_scene, synthetic_scene.query_images[0]))
    assert loaded.prepared.wait(60)
    state = loaded.map.snapshot()
    after = held_pool(state, "orb", IndexConf(exact_rows=0))
    assert after is not None, "the pool was not made at load"
    assert not made, "the stored index was trained again"
    np.testing.assert_array_equal(after.index.order, before.index.order)
    np.testing.assert_array_equal(after.index.offsets, before.index.offsets)
    assert loaded.held_bytes() == after.nbytes + statistics_bytes(state) > 0


def test_a_load_builds_the_pool_before_the_first_query_when_none_fits(saved, monkeypatch
                                                                      ) -> None:
    _, directory = saved
    made = count_builds(monkeypatch)
    loaded = Engine.load(directory, conf(1))   # other options than the stored index's
    assert loaded.prepared.wait(60)
    built = held_pool(loaded.map.snapshot(), "orb", IndexConf(exact_rows=1))
    assert built is not None and built.index.tree is not None
    assert made == [1]


def test_the_index_read_gives_the_answers_of_the_index_built(saved, synthetic_scene) -> None:
    _, directory = saved
    read = Engine.load(directory, conf(0))
    built = Engine.load(directory, conf(1))   # an index of its own, built at load
    assert read.prepared.wait(60) and built.prepared.wait(60)
    for image in synthetic_scene.query_images:
        a = read.relocalize(_frame(synthetic_scene, image))
        b = built.relocalize(_frame(synthetic_scene, image))
        assert (a.ok, a.reason) == (b.ok, b.reason)
        if a.ok:
            np.testing.assert_allclose(a.world_from_cam, b.world_from_cam, atol=1e-9)


def test_a_damaged_stored_index_is_refused_by_name(saved, tmp_path) -> None:
    import shutil

    _, directory = saved
    copy = tmp_path / "map"
    shutil.copytree(directory, copy)
    path = stored_index(copy)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(StorageError, match="repetition/orb.leaves.npz"):
        Engine.load(copy, conf(0))


def _frame(scene, image):
    from reloc_service.core.frame import Frame

    return Frame(image=image, camera=scene.camera)


def test_two_threads_asking_for_a_pool_at_once_share_one_build(saved, monkeypatch) -> None:
    import dataclasses

    from reloc_service.algorithms.pose.map_pool import map_pool

    engine, _ = saved
    state = dataclasses.replace(engine.map.snapshot())   # a state no pool is made for yet
    made = count_builds(monkeypatch)
    got: list[object] = []
    threads = [threading.Thread(target=lambda: got.append(
        map_pool(state, "orb", IndexConf(exact_rows=0)))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert len(got) == 3 and got[0] is got[1] is got[2]
    assert made == [1]


def test_an_engine_that_answers_no_query_starts_no_pool_work(saved) -> None:
    _, directory = saved

    def pool_threads() -> set[threading.Thread]:
        return {t for t in threading.enumerate() if t.name == "map-pools"}

    already = pool_threads()
    loaded = Engine.load(directory, conf(0), pools=False)   # a service's, with worker processes
    assert loaded.prepared.is_set()
    assert not pool_threads() - already


def test_the_pool_digest_is_the_same_in_chunks_and_checks_its_cancel_between_them(
        monkeypatch) -> None:
    from reloc_service.algorithms.pose import repetition_store
    from reloc_service.core.errors import Cancelled

    rows = np.random.default_rng(0).integers(0, 256, (5000, 128), dtype=np.uint8)
    whole = repetition_store.pool_digest(rows)
    monkeypatch.setattr(repetition_store, "DIGEST_CHUNK_BYTES", 4096)
    checks = []
    assert np.array_equal(repetition_store.pool_digest(rows, lambda: checks.append(1) or False),
                          whole)
    assert len(checks) == rows.nbytes // 4096 + 1   # 640000 bytes in 157 chunks
    assert not np.array_equal(repetition_store.pool_digest(rows[:-1]), whole)
    with pytest.raises(Cancelled):
        repetition_store.pool_digest(rows, lambda: True)
