"""The map store of the service (journal, snapshots, service.json) without Zenoh or a runtime."""

import json

import pytest

from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import StorageError
from reloc_service.engine import Engine, EngineConf
from reloc_service.service.durability import SERVICE_FILE, MapStore, RestoreReport, ServiceMeta, open_engine
from reloc_service.service.map_dirs import (
    MAP_NAME_FILE,
    map_dirname,
    map_name_of,
    record_map_name,
    stored_map_names,
)
from reloc_service.service.restore_verdict import judge

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)


def opened(directory, **kw) -> tuple[MapStore, list[dict]]:
    """A store on ``directory`` restored as the runtime does it; the records it replayed."""
    store = MapStore("m", directory, **kw)
    applied: list[dict] = []
    store.replay(judge(directory), applied.append, RestoreReport())
    return store, applied


def test_records_replay_in_order_and_count_towards_the_next_snapshot(tmp_path):
    store, applied = opened(tmp_path, snapshot_every=3)
    assert applied == []
    for i in range(3):
        assert not store.wants_snapshot()
        store.append({"op": "del", "id": i})
    assert store.wants_snapshot()
    store.close()
    store, applied = opened(tmp_path, snapshot_every=3)
    assert applied == [{"op": "del", "id": i, "seq": i + 1} for i in range(3)]
    assert store.since_snapshot == 3 and store.wants_snapshot()
    store.close()


def test_a_record_that_does_not_apply_is_skipped_and_counted(tmp_path):
    store, _ = opened(tmp_path)
    for i in range(3):
        store.append({"op": "del", "id": i})
    store.close()

    def apply(record: dict) -> None:
        if record["id"] == 1:
            raise ValueError("keyframe 1 does not decode")

    report = RestoreReport()
    MapStore("m", tmp_path).replay(judge(tmp_path), apply, report)
    assert (report.replayed, report.not_applied) == (2, 1)
    assert report.damaged and report.counters()["restore_records_not_applied"] == 1


def test_a_snapshot_names_itself_and_drops_the_journal_before_it(tmp_path):
    store, _ = opened(tmp_path)
    store.append({"op": "cam", "id": "cam0", "payload": b"old"})
    engine = Engine(EngineConf())
    segment = store.rotate()
    assert store.since_snapshot == 0
    store.append({"op": "del", "id": 7})    # arrives during the save: kept in the journal
    path = store.save(engine, ServiceMeta(cameras={"cam0": CAMERA},
                                          keyframe_camera_ids={3: "cam0"},
                                          next_segment=segment))
    store.close()
    written = json.loads((tmp_path / SERVICE_FILE).read_text())
    assert written["snapshot"] == path.name and written["next_segment"] == segment
    assert store.journal.segments() == [segment]
    store, applied = opened(tmp_path)
    meta = store.read_meta()
    assert meta.cameras["cam0"].to_dict() == CAMERA.to_dict()
    assert meta.keyframe_camera_ids == {3: "cam0"}
    assert applied == [{"op": "del", "id": 7, "seq": 2}]    # the camera (1) is in the snapshot
    store.close()
    assert open_engine(tmp_path, EngineConf()).map.snapshot().version == \
        engine.map.snapshot().version


@pytest.mark.parametrize("content, expected", [
    ("{not json", "cannot read"),
    ('["a list"]', "expected a JSON object"),
    ('{"cameras": {"cam0": {"model": "nope"}}}', "expected cameras, keyframe_camera_ids"),
    ('{"next_segment": "first"}', "expected cameras, keyframe_camera_ids"),
])
def test_a_damaged_service_file_is_a_storage_error_naming_it(tmp_path, content, expected):
    (tmp_path / SERVICE_FILE).write_text(content)
    with pytest.raises(StorageError) as err:
        MapStore("m", tmp_path).read_meta()
    assert SERVICE_FILE in str(err.value) and expected in str(err.value)


def test_map_directories_round_trip_their_names(tmp_path):
    names = ["room", ".hidden", "a b/c", "..", "drone_1"]
    for name in names:
        dirname = map_dirname(name)
        assert dirname not in (".", "..") and "/" not in dirname
        assert map_name_of(dirname) == name
    for name in ("room", ".hidden", "drone_1"):
        (tmp_path / map_dirname(name) / "journal").mkdir(parents=True)
    (tmp_path / "no-journal-or-map").mkdir()      # not a map directory: not listed
    assert sorted(stored_map_names(tmp_path)) == sorted([".hidden", "drone_1", "room"])


#: Names the protocol accepts (at most 128 characters) whose percent-encoding exceeds NAME_MAX.
LONG_NAMES = ["\ud55c" * 30, "\U0001f681" * 64, "%" * 128, "." + "\u00e9" * 127]


@pytest.mark.parametrize("name", LONG_NAMES)
def test_long_map_names_get_directory_names_that_fit_and_keep_a_readable_prefix(tmp_path,
                                                                                 name):
    dirname = map_dirname(name)
    assert len(dirname.encode()) <= 255 and dirname not in (".", "..") and "/" not in dirname
    prefix, digest = dirname.rsplit("+", 1)
    assert len(digest) == 32                               # BLAKE2b of the whole name
    assert name.startswith(map_name_of(prefix)) and len(map_name_of(prefix)) >= 10
    (tmp_path / dirname / "journal").mkdir(parents=True)     # the file system takes it
    record_map_name(tmp_path / dirname, name)
    assert stored_map_names(tmp_path) == [name]


def test_short_names_keep_their_percent_encoded_directory_names():
    assert map_dirname("lab") == "lab"
    assert map_dirname(".hidden") == "%2Ehidden"
    assert map_dirname("caf\u00e9") == "caf%C3%A9"
    name = "\u00e9" * 42                     # 252 encoded bytes: still fits, stays readable
    assert map_dirname(name) == "%C3%A9" * 42


def test_long_names_sharing_a_prefix_get_different_directories():
    names = ["\ud55c" * 29 + c for c in "abc"] + ["\ud55c" * 30]
    assert len({map_dirname(n) for n in names}) == len(names)


def test_a_directory_holding_another_map_is_refused_by_name(tmp_path):
    directory = tmp_path / map_dirname("\ud55c" * 30)
    (directory / "journal").mkdir(parents=True)
    record_map_name(directory, "\ud55c" * 30)
    with pytest.raises(StorageError, match="holds map .* not 'other'"):
        record_map_name(directory, "other")
    (directory / MAP_NAME_FILE).write_text("other")   # a record naming another directory's map
    assert stored_map_names(tmp_path) == []


def test_a_hashed_directory_without_its_recorded_name_is_left_alone(tmp_path):
    (tmp_path / map_dirname("%" * 128) / "journal").mkdir(parents=True)
    assert stored_map_names(tmp_path) == []
