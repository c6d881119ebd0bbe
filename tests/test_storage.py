"""Map persistence: exact round trip, atomic snapshots, pruning, and clear errors for damaged
or newer maps."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from map_state_support import assert_states_equal, enriched_state, tiny_state
from stored_maps import stored_map

from reloc_service.core.errors import StorageError
from reloc_service.core.file_mapping import is_mapped
from reloc_service.core.frame import EncodedImage, Keyframe
from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.storage import snapshot as storage
from reloc_service.storage import snapshot_files
from reloc_service.storage.feature_columns import LazyFeatures
from reloc_service.storage.landmark_codec import (
    AnchoredPoints,
    WidenedColumn,
)
from reloc_service.storage.snapshot import (
    current_snapshot,
    load_map,
    model_dir_name,
    save_map,
    saved_models,
)


@pytest.fixture(scope="module")
def rich_state(synthetic_scene, synthetic_map) -> MapState:
    """The synthetic map with a depth map, a timestamp-less keyframe and ORB features too."""
    return enriched_state(synthetic_scene, synthetic_map)



def test_round_trip_is_exact(tmp_path, rich_state):
    written = []

    def write_model(directory: Path) -> None:
        written.append(directory)
        (directory / "model.bin").write_bytes(b"\x00\x01model")
        (directory / "sub").mkdir()
        (directory / "sub" / "more.json").write_text("{}")

    snapshot = save_map(rich_state, tmp_path / "map", models={"sbi+p3p": write_model})
    assert snapshot == current_snapshot(tmp_path / "map")
    assert written == [snapshot / "models" / model_dir_name("sbi+p3p")]
    state, models = load_map(tmp_path / "map")
    assert_states_equal(rich_state, state)
    assert state.keyframes[9].timestamp is None and state.keyframes[0].timestamp == 0.0
    assert state.keyframes[9].depth is not None
    assert models == snapshot / "models"
    assert (models / "sbi+p3p" / "model.bin").read_bytes() == b"\x00\x01model"
    assert saved_models(tmp_path / "map") == {"sbi+p3p": models / "sbi+p3p"}
    # The loaded state works as a map.
    kmap = KeyframeMap()
    kmap.replace_state(state)
    kmap.remove_keyframe(0)


def test_pose_covariances_round_trip_and_a_bad_one_is_named(tmp_path, synthetic_map):
    """A keyframe's pose covariance is saved as given (none stays none); a manifest whose
    covariance is not one (not positive semi-definite) fails the load naming the keyframe."""
    kmap = KeyframeMap()
    kmap.replace_state(tiny_state(synthetic_map, 2))
    first = kmap.snapshot().keyframes[0]
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5])
    cov[1, 4] = cov[4, 1] = 1e-5
    kmap.add_keyframe(dataclasses.replace(first, image=first.image_source, pose_covariance=cov))
    snap = save_map(kmap.snapshot(), tmp_path)
    state, _ = load_map(tmp_path)
    np.testing.assert_array_equal(state.keyframes[0].pose_covariance, cov)
    assert state.keyframes[1].pose_covariance is None
    manifest = json.loads((snap / "manifest.json").read_text())
    entry = next(e for e in manifest["keyframes"] if e["id"] == 0)
    entry["pose_covariance"] = np.diag([1e-4] * 5 + [-1e-4]).tolist()
    (snap / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(StorageError, match=r"keyframe 0: pose_covariance: .*positive semi-def"):
        load_map(tmp_path)


def test_empty_map_round_trip(tmp_path):
    save_map(MapState(), tmp_path)
    state, models = load_map(tmp_path)
    assert_states_equal(MapState(), state)
    assert models is None


def test_model_dir_names_are_safe():
    assert model_dir_name("sbi+p3p") == "sbi+p3p"
    assert model_dir_name("bow+p3p,sbi+esm") == "bow+p3p,sbi+esm"
    assert "/" not in model_dir_name("../x/y") and model_dir_name("") == "_"


def test_older_snapshots_are_pruned(tmp_path, synthetic_map):
    for n in (1, 2, 3):
        save_map(tiny_state(synthetic_map, n), tmp_path)
    names = sorted(p.name for p in (tmp_path / "snapshots").iterdir())
    assert names == ["000002", "000003"]
    assert len(load_map(tmp_path)[0].keyframes) == 3


def test_crash_in_a_model_writer_keeps_the_previous_snapshot(tmp_path, synthetic_map):
    first = tiny_state(synthetic_map, 2)
    save_map(first, tmp_path)

    def crash(directory: Path) -> None:
        (directory / "half.bin").write_bytes(b"x")
        raise KeyboardInterrupt("power cut")

    with pytest.raises(KeyboardInterrupt):
        save_map(synthetic_map, tmp_path, models={"m": crash})
    state, _ = load_map(tmp_path)
    assert_states_equal(first, state)
    # The next save replaces the debris.
    save_map(synthetic_map, tmp_path)
    assert_states_equal(synthetic_map, load_map(tmp_path)[0])
    assert len(list((tmp_path / "snapshots").iterdir())) == 2


@pytest.mark.parametrize("when", ["manifest", "switch"])
def test_crash_before_the_switch_keeps_the_previous_snapshot(tmp_path, synthetic_map, monkeypatch,
                                                             when):
    first = tiny_state(synthetic_map, 2)
    save_map(first, tmp_path)

    def boom(*args, **kwargs):
        raise OSError("disk full")

    if when == "switch":
        monkeypatch.setattr(storage.os, "replace", boom)
    else:
        real_write = snapshot_files.SnapshotWriter.write

        def write(self, relpath, data):
            if relpath == snapshot_files.MANIFEST_FILE:
                real_write(self, relpath, data[: len(data) // 2])
                raise OSError("crash while writing the manifest")
            return real_write(self, relpath, data)

        monkeypatch.setattr(snapshot_files.SnapshotWriter, "write", write)
    with pytest.raises(OSError):
        save_map(synthetic_map, tmp_path)
    monkeypatch.undo()
    assert_states_equal(first, load_map(tmp_path)[0])


@pytest.fixture(scope="module")
def saved_two(tmp_path_factory, synthetic_map) -> Path:
    """A map directory holding the first two keyframes of the synthetic map and a model
    ``m``, saved once per module: :func:`_saved` gives each test a copy to damage."""
    directory = tmp_path_factory.mktemp("saved_two")
    save_map(tiny_state(synthetic_map, 2), directory,
             models={"m": lambda d: (d / "w").write_text("1")})
    return directory


def _saved(tmp_path: Path, saved_two: Path) -> Path:
    """A copy of ``saved_two`` in ``tmp_path`` (a file copy: what a save wrote, byte for
    byte); its current snapshot."""
    shutil.copytree(saved_two, tmp_path, dirs_exist_ok=True)
    return current_snapshot(tmp_path)


def test_truncated_file_is_named(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    path = snap / "features" / "sift.keypoints_px.npy"
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(StorageError, match=r"sift\.keypoints_px\.npy.*truncated"):
        load_map(tmp_path)


def test_equal_model_files_of_two_methods_are_stored_once(tmp_path, rich_state):
    """Two methods holding the same trained model (bytes equal) share its file: one inode,
    each method's path reads its bytes, the manifest still lists both with their checksum."""
    def writer(data: bytes):
        def write(directory: Path) -> None:
            (directory / "place.bin").write_bytes(data)
            (directory / "own.bin").write_bytes(data[::-1] + directory.name.encode())
        return write

    same = bytes(range(256)) * 40
    models = {"bow+p3p": writer(same), "sbi+p3p,bow+p3p": writer(same), "other": writer(b"x" * 99)}
    save_map(rich_state, tmp_path / "map", models=models)
    state, root = load_map(tmp_path / "map")            # every checksum verified
    assert root is not None
    paths = {m: p / "place.bin" for m, p in saved_models(tmp_path / "map").items()}
    first, second, other = (os.stat(paths[m]) for m in models)
    assert first.st_ino == second.st_ino and first.st_nlink == 2
    assert other.st_ino != first.st_ino and other.st_nlink == 1
    assert paths["sbi+p3p,bow+p3p"].read_bytes() == same
    owns = {os.stat(p.parent / "own.bin").st_ino for p in paths.values()}
    assert len(owns) == 3                                # different bytes: stored apart
    manifest = json.loads((current_snapshot(tmp_path / "map") / "manifest.json").read_text())
    assert sum(rel.endswith("/place.bin") for rel in manifest["files"]) == 3


def test_checksum_mismatch_is_named(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    path = snap / "landmarks" / "anchored_points_world.npy"
    data = bytearray(path.read_bytes())
    data[-10] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(StorageError, match=r"anchored_points_world\.npy.*checksum mismatch"):
        load_map(tmp_path)


def test_flipped_byte_in_a_mapped_image_is_named(tmp_path, saved_two):
    # images are hashed from their memory map at load (not read()): one flipped bit must fail
    snap = _saved(tmp_path, saved_two)
    image = snap / "images" / "0.png"
    data = bytearray(image.read_bytes())
    data[len(data) // 2] ^= 0x01
    image.write_bytes(bytes(data))
    with pytest.raises(StorageError, match=r"images/0\.png.*checksum mismatch"):
        load_map(tmp_path)


def test_damaged_model_file_is_named(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    (snap / "models" / "m" / "w").write_text("2")
    with pytest.raises(StorageError, match=r"models/m/w.*checksum"):
        load_map(tmp_path)


def test_missing_file_is_named(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    (snap / "images" / "0.png").unlink()
    with pytest.raises(StorageError, match=r"0\.png.*cannot read"):
        load_map(tmp_path)


def test_bad_manifest_json(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    (snap / "manifest.json").write_text("{not json")
    with pytest.raises(StorageError, match=r"manifest\.json.*not valid JSON"):
        load_map(tmp_path)


def _edit_manifest(snap: Path, **changes) -> None:
    manifest = json.loads((snap / "manifest.json").read_text())
    manifest.update(changes)
    (snap / "manifest.json").write_text(json.dumps(manifest))


def test_newer_format_version_is_refused(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    _edit_manifest(snap, format_version=storage.FORMAT_VERSION + 1)
    newer = storage.FORMAT_VERSION + 1
    with pytest.raises(StorageError, match=rf"newer reloc .*format version {newer}.*reads up "
                                           rf"to {storage.FORMAT_VERSION}"):
        load_map(tmp_path)


def test_wrong_format_and_fields(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    _edit_manifest(snap, format="something else")
    with pytest.raises(StorageError, match="expected 'reloc map'"):
        load_map(tmp_path)
    _edit_manifest(snap, format=storage.FORMAT, keyframes={"0": 1})
    with pytest.raises(StorageError, match="'keyframes' missing or not a list"):
        load_map(tmp_path)


def test_bad_keyframe_entry_is_named(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    manifest = json.loads((snap / "manifest.json").read_text())
    manifest["keyframes"][1]["world_from_cam"] = [[1, 0, 0]]
    (snap / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(StorageError, match=r"keyframe 1.*world_from_cam"):
        load_map(tmp_path)


def test_missing_or_bad_current(tmp_path, saved_two):
    with pytest.raises(StorageError, match="no saved map.*CURRENT"):
        load_map(tmp_path)
    _saved(tmp_path, saved_two)
    (tmp_path / "CURRENT").write_text("../../etc\n")
    with pytest.raises(StorageError, match="CURRENT.*expected 'snapshots/<number>'"):
        load_map(tmp_path)
    (tmp_path / "CURRENT").write_text("snapshots/000099\n")
    with pytest.raises(StorageError, match="does not exist"):
        load_map(tmp_path)


def test_saved_files_are_synced_before_the_switch(tmp_path, synthetic_map, monkeypatch):
    """Every written file and directory is fsynced before CURRENT is replaced."""
    events: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(storage.os, "fsync", lambda fd: (events.append("fsync"), real_fsync(fd))[1])
    def replace(a, b):
        events.append(f"replace {Path(b).name}")
        real_replace(a, b)

    monkeypatch.setattr(storage.os, "replace", replace)
    save_map(tiny_state(synthetic_map, 2), tmp_path)
    switch = events.index("replace CURRENT")
    files = [p for p in current_snapshot(tmp_path).rglob("*")]
    assert events[:switch].count("fsync") >= len(files) + 1
    assert events[switch + 1:] == ["fsync"]           # the directory, after the rename


def test_keyframe_type_survives(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path)
    state, _ = load_map(tmp_path)
    assert all(isinstance(kf, Keyframe) for kf in state.keyframes.values())


def test_round_trip_keeps_depth_sigmas(tmp_path, rich_state):
    sigmas = [lm.depth_sigma_m for lm in rich_state.landmarks.values()]
    assert any(s > 0 for s in sigmas)          # triangulated landmarks carry their uncertainty
    save_map(rich_state, tmp_path / "new")
    state, _ = load_map(tmp_path / "new")
    assert_states_equal(rich_state, state)



def test_format_1_snapshots_are_read(tmp_path):
    """A snapshot written by format 1 (PNG images, .npz per keyframe; made by the code of
    that version, kept in tests/data) loads into the same map, and saves as format 2."""
    state, models = load_map(stored_map(1))
    assert models is None and state.keyframe_ids() == [0, 1]
    assert sorted(state.landmarks) == [0, 1, 2]
    assert state.landmarks[0].observations == frozenset({(0, "sift", 0), (1, "sift", 1)})
    assert state.landmark_sigmas([0, 1, 2]).tolist() == [0.1, 0.0, 0.2]
    assert state.keyframes[1].features["sift"].landmark_ids[4] == 2
    v1_desc = np.load(stored_map(1) / "snapshots" / "000001" / "features" / "1.sift.npz")["descriptors"]
    assert v1_desc.dtype == np.float32                # compacted on read, exactly
    assert np.array_equal(state.keyframes[1].features["sift"].descriptors, v1_desc)
    assert state.keyframes[1].features["sift"].descriptors.dtype == np.uint8
    save_map(state, tmp_path)
    again, _ = load_map(tmp_path)
    assert_states_equal(state, again)


def test_format_0_or_unknown_versions_are_refused(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    _edit_manifest(snap, format_version=0)
    with pytest.raises(StorageError, match="format_version 0, expected a positive integer"):
        load_map(tmp_path)


def _maps_a_file(a: np.ndarray) -> bool:
    """``a`` views (through views...) a file's memory map: it reads the file, no copy."""
    return is_mapped(a)


def test_loaded_arrays_are_read_only_memory_maps(tmp_path, rich_state):
    """Nothing is rebuilt at load: images, features, landmarks and thumbnails are views of
    the snapshot's files, read-only."""
    for kf in rich_state.keyframes.values():
        kf.small_blurry_image()                       # what the sbi place finder caches
    save_map(rich_state, tmp_path)
    state, _ = load_map(tmp_path)
    kf = state.keyframes[1]
    image = kf.image_source                           # PNG, decoded on first use
    assert isinstance(image, EncodedImage) and not image.data.flags.writeable
    assert is_mapped(image.data)
    pixels = kf.image
    assert np.array_equal(pixels, rich_state.keyframes[1].image)
    assert kf.image_source is image                   # a keyframe stays encoded ...
    assert kf.image is pixels and not pixels.flags.writeable   # ... its pixels shared, read-only
    assert isinstance(kf.features, LazyFeatures) and "built=[]" in repr(kf.features)
    # stored in their own dtype: views of the files; narrowed or derived (keypoints float32
    # on disk, ids and points from the landmarks, ORB sizes from the levels): read-only
    # arrays made for this keyframe only
    arrays = [*(kf.features[k].descriptors for k in kf.features), kf.features["sift"].sizes,
              kf.cache["sbi:40x30:2.5"]]
    for a in arrays:
        assert _maps_a_file(a), type(a)
        assert not a.flags.writeable
    for k in kf.features:
        for f in ("keypoints_px", "levels", "landmark_ids", "points_world", "sizes", "angles"):
            assert not getattr(kf.features[k], f).flags.writeable
    columns = state.landmarks.columns()   # ids, indices: stored narrow, widened at load
    # points and sigmas: float32 files, still mapped, float64 rows decoded on read
    assert isinstance(columns.points_world, AnchoredPoints)
    assert isinstance(columns.depth_sigmas_m, WidenedColumn)
    assert _maps_a_file(columns.points_world._offsets)
    assert _maps_a_file(columns.depth_sigmas_m._column)
    rows = np.array([3, 0, 7])
    assert columns.points_world[rows].dtype == np.float64
    assert np.array_equal(columns.points_world[rows], np.asarray(columns.points_world)[rows])
    assert np.array_equal(columns.depth_sigmas_m[rows], np.asarray(columns.depth_sigmas_m)[rows])
    for name, dtype in storage.LANDMARK_DTYPES.items():
        assert getattr(columns, name).dtype == dtype and not getattr(columns, name).flags.writeable
    assert "built=[]" in repr(state.keyframes[0].features)       # untouched: nothing made
    assert np.array_equal(kf.cache["sbi:40x30:2.5"], rich_state.keyframes[1].cache["sbi:40x30:2.5"])
    with pytest.raises(ValueError, match="read-only"):
        kf.features["sift"].descriptors[0, 0] = 1


def test_changing_a_loaded_map_copies_and_leaves_the_snapshot(tmp_path, rich_state,
                                                               synthetic_scene):
    """Copy on write over memory-mapped arrays: adding and removing keyframes works, and the
    snapshot's files are byte-for-byte what was saved."""
    from reloc_service.core.mapping import MapBuilder

    snap = save_map(rich_state, tmp_path)
    before = {p: p.read_bytes() for p in snap.rglob("*") if p.is_file()}
    state, _ = load_map(tmp_path)
    kmap = KeyframeMap()
    kmap.replace_state(state)
    builder = MapBuilder(kmap)
    builder.add_keyframe(20, synthetic_scene.query_images[1], synthetic_scene.camera,
                         synthetic_scene.query_poses[1])
    kmap.remove_keyframe(0)
    after = kmap.snapshot()
    assert len(after.landmarks) > 0 and 20 in after.keyframes and 0 not in after.keyframes
    assert storage.verify_snapshot(snap) == len(before) - 1     # manifest not listed
    assert {p: p.read_bytes() for p in snap.rglob("*") if p.is_file()} == before
    again, _ = load_map(tmp_path)
    assert_states_equal(state, again)


def test_a_save_without_current_deletes_no_snapshot(tmp_path, synthetic_map, saved_two):
    """``CURRENT`` deleted, then a save of an (empty) map must not remove the snapshot holding
    the keyframes (docs/reliability.md, fault case 4)."""
    old = _saved(tmp_path, saved_two)
    (tmp_path / "CURRENT").unlink()
    new = save_map(tiny_state(synthetic_map, 0), tmp_path)
    assert old.is_dir()
    assert storage.verify_snapshot(old) > 0
    assert [p.name for p in snapshot_files.snapshot_dirs(tmp_path)] == [old.name, new.name]
    newest = save_map(tiny_state(synthetic_map, 1), tmp_path)   # CURRENT back: ancestors go
    assert [p.name for p in snapshot_files.snapshot_dirs(tmp_path)] == [new.name, newest.name]


def test_restore_current_verifies_the_snapshot_first(tmp_path, saved_two):
    snap = _saved(tmp_path, saved_two)
    (tmp_path / "CURRENT").unlink()
    assert storage.restore_current(tmp_path, snap.name) == snap
    assert len(load_map(tmp_path)[0].keyframes) == 2
    with pytest.raises(StorageError, match="exists"):
        storage.restore_current(tmp_path, snap.name)
    (tmp_path / "CURRENT").unlink()
    image = next((snap / "images").iterdir())
    data = bytearray(image.read_bytes())
    data[len(data) // 2] ^= 0x01
    image.write_bytes(bytes(data))
    with pytest.raises(StorageError, match="checksum mismatch"):
        storage.restore_current(tmp_path, snap.name)
    assert not (tmp_path / "CURRENT").exists()
