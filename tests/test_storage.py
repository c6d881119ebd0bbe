"""Map persistence: exact round trip, atomic snapshots, pruning, and clear errors for damaged
or newer maps."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from reloc_service.core.errors import StorageError
from reloc_service.core.file_mapping import is_mapped
from reloc_service.core.frame import EncodedImage, Keyframe
from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.storage import snapshot as storage
from reloc_service.storage import snapshot_files
from reloc_service.storage.feature_columns import ANGLELESS_KINDS, NO_ANGLE, LazyFeatures
from reloc_service.storage.landmark_codec import (
    ROUNDING_SHARE,
    AnchoredPoints,
    WidenedColumn,
    anchors,
    position_sigmas,
)
from reloc_service.storage.snapshot import (
    FEATURE_FIELDS,
    current_snapshot,
    load_map,
    model_dir_name,
    save_map,
    saved_models,
)


def _assert_states_equal(a: MapState, b: MapState) -> None:
    """``b`` is ``a`` exactly, but for landmark points and sigmas: exact, or (stored as
    anchored float32) within the rounding :mod:`reloc_service.storage.landmark_codec` allows."""
    assert (a.version, a.next_landmark_id) == (b.version, b.next_landmark_id)
    assert a.keyframe_ids() == b.keyframe_ids()
    for k in a.keyframe_ids():
        ka, kb = a.keyframes[k], b.keyframes[k]
        assert ka.camera == kb.camera and ka.timestamp == kb.timestamp
        assert np.array_equal(ka.world_from_cam, kb.world_from_cam)
        assert np.array_equal(ka.image, kb.image) and kb.image.dtype == np.uint8
        assert (ka.depth is None) == (kb.depth is None)
        if ka.depth is not None:
            assert np.array_equal(ka.depth, kb.depth, equal_nan=True)
        assert sorted(ka.features) == sorted(kb.features)
        for kind in ka.features:
            for name in FEATURE_FIELDS:
                va, vb = getattr(ka.features[kind], name), getattr(kb.features[kind], name)
                assert va.dtype == vb.dtype, name
                if name == "points_world":
                    va = _as_loaded_points(a, b, ka.features[kind].landmark_ids, va, vb)
                if name == "angles" and kind in ANGLELESS_KINDS:   # not saved: OpenCV's "none"
                    va = np.full_like(va, NO_ANGLE)
                assert np.array_equal(va, vb, equal_nan=True), name
    assert sorted(a.landmarks) == sorted(b.landmarks)
    for i, lm in a.landmarks.items():
        assert lm.observations == b.landmarks[i].observations
    _assert_landmark_geometry_close(a, b)


def _as_loaded_points(a: MapState, b: MapState, ids: np.ndarray, points: np.ndarray,
                      loaded: np.ndarray) -> np.ndarray:
    """``points`` with each that is its landmark's point in ``a`` and was not loaded as it
    is (not a stored column) replaced by that landmark's point in ``b``: derived at load."""
    out = points.copy()
    has = np.flatnonzero((ids >= 0) & a.landmarks.contains(ids))
    derived = (np.all(a.landmark_points(ids[has]) == points[has], axis=1)
               & ~np.all(loaded[has] == points[has], axis=1))
    out[has[derived]] = b.landmark_points(ids[has[derived]])
    return out


def _assert_landmark_geometry_close(a: MapState, b: MapState) -> None:
    ids = np.array(sorted(a.landmarks), np.int64)
    pa, pb = a.landmark_points(ids), b.landmark_points(ids)
    sa, sb = a.landmark_sigmas(ids), b.landmark_sigmas(ids)
    found = anchors(a.landmarks.columns(), a.keyframes)
    if found is None:
        assert np.array_equal(pa, pb) and np.array_equal(sa, sb)
        return
    allowed = ROUNDING_SHARE * position_sigmas(pa, *found, sa)
    assert np.all(np.linalg.norm(pa - pb, axis=1) <= allowed)
    assert np.all(np.abs(sa - sb) <= allowed)


@pytest.fixture(scope="module")
def rich_state(synthetic_scene, synthetic_map) -> MapState:
    """The synthetic map with a depth map, a timestamp-less keyframe and ORB features too."""
    from reloc_service.core.features import FeatureConf, extract
    from reloc_service.core.mapping import MapBuilder

    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    kf = synthetic_map.keyframes[1]
    kmap.add_keyframe(kf.with_features("orb", extract(kf.image, FeatureConf("orb", 300))))
    MapBuilder(kmap).add_keyframe(9, synthetic_scene.query_images[0], synthetic_scene.camera,
                                  synthetic_scene.query_poses[0],
                                  depth=synthetic_scene.query_depths[0])
    return kmap.snapshot()


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
    _assert_states_equal(rich_state, state)
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
    kmap.replace_state(_tiny_state(synthetic_map, 2))
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
    _assert_states_equal(MapState(), state)
    assert models is None


def test_model_dir_names_are_safe():
    assert model_dir_name("sbi+p3p") == "sbi+p3p"
    assert model_dir_name("bow+p3p,sbi+esm") == "bow+p3p,sbi+esm"
    assert "/" not in model_dir_name("../x/y") and model_dir_name("") == "_"


def _tiny_state(synthetic_map: MapState, n: int) -> MapState:
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    for k in synthetic_map.keyframe_ids()[n:]:
        kmap.remove_keyframe(k)
    return kmap.snapshot()


def test_older_snapshots_are_pruned(tmp_path, synthetic_map):
    for n in (1, 2, 3):
        save_map(_tiny_state(synthetic_map, n), tmp_path)
    names = sorted(p.name for p in (tmp_path / "snapshots").iterdir())
    assert names == ["000002", "000003"]
    assert len(load_map(tmp_path)[0].keyframes) == 3


def test_crash_in_a_model_writer_keeps_the_previous_snapshot(tmp_path, synthetic_map):
    first = _tiny_state(synthetic_map, 2)
    save_map(first, tmp_path)

    def crash(directory: Path) -> None:
        (directory / "half.bin").write_bytes(b"x")
        raise KeyboardInterrupt("power cut")

    with pytest.raises(KeyboardInterrupt):
        save_map(synthetic_map, tmp_path, models={"m": crash})
    state, _ = load_map(tmp_path)
    _assert_states_equal(first, state)
    # The next save replaces the debris.
    save_map(synthetic_map, tmp_path)
    _assert_states_equal(synthetic_map, load_map(tmp_path)[0])
    assert len(list((tmp_path / "snapshots").iterdir())) == 2


@pytest.mark.parametrize("when", ["manifest", "switch"])
def test_crash_before_the_switch_keeps_the_previous_snapshot(tmp_path, synthetic_map, monkeypatch,
                                                             when):
    first = _tiny_state(synthetic_map, 2)
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
    _assert_states_equal(first, load_map(tmp_path)[0])


@pytest.fixture(scope="module")
def saved_two(tmp_path_factory, synthetic_map) -> Path:
    """A map directory holding the first two keyframes of the synthetic map and a model
    ``m``, saved once per module: :func:`_saved` gives each test a copy to damage."""
    directory = tmp_path_factory.mktemp("saved_two")
    save_map(_tiny_state(synthetic_map, 2), directory,
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
    save_map(_tiny_state(synthetic_map, 2), tmp_path)
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
    _assert_states_equal(rich_state, state)


V1_MAP = Path(__file__).parent / "data" / "map_v1"


def test_format_1_snapshots_are_read(tmp_path):
    """A snapshot written by format 1 (PNG images, .npz per keyframe; made by the code of
    that version, kept in tests/data) loads into the same map, and saves as format 2."""
    state, models = load_map(V1_MAP)
    assert models is None and state.keyframe_ids() == [0, 1]
    assert sorted(state.landmarks) == [0, 1, 2]
    assert state.landmarks[0].observations == frozenset({(0, "sift", 0), (1, "sift", 1)})
    assert state.landmark_sigmas([0, 1, 2]).tolist() == [0.1, 0.0, 0.2]
    assert state.keyframes[1].features["sift"].landmark_ids[4] == 2
    v1_desc = np.load(V1_MAP / "snapshots" / "000001" / "features" / "1.sift.npz")["descriptors"]
    assert v1_desc.dtype == np.float32                # compacted on read, exactly
    assert np.array_equal(state.keyframes[1].features["sift"].descriptors, v1_desc)
    assert state.keyframes[1].features["sift"].descriptors.dtype == np.uint8
    save_map(state, tmp_path)
    again, _ = load_map(tmp_path)
    _assert_states_equal(state, again)


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
    arrays = [*(kf.features[k].descriptors for k in kf.features), kf.features["sift"].angles,
              kf.features["sift"].sizes,
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
    _assert_states_equal(state, again)


def test_a_save_without_current_deletes_no_snapshot(tmp_path, synthetic_map, saved_two):
    """``CURRENT`` deleted, then a save of an (empty) map must not remove the snapshot holding
    the keyframes (docs/reliability.md, fault case 4)."""
    old = _saved(tmp_path, saved_two)
    (tmp_path / "CURRENT").unlink()
    new = save_map(_tiny_state(synthetic_map, 0), tmp_path)
    assert old.is_dir()
    assert storage.verify_snapshot(old) > 0
    assert [p.name for p in snapshot_files.snapshot_dirs(tmp_path)] == [old.name, new.name]
    newest = save_map(_tiny_state(synthetic_map, 1), tmp_path)   # CURRENT back: ancestors go
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


# -- format 3: narrow columns, derived points, images as sent ---------------------------------

V2_MAP = Path(__file__).parent / "data" / "map_v2"


def _snapshot_npy(snapshot: Path, rel: str) -> np.ndarray:
    """The column ``rel`` (``<stem>.npy``) as stored: raw, or packed by format 7."""
    from reloc_service.storage.packed_columns import DELTA_PACKED, SUFFIXES, unpack

    stem = rel.removesuffix(".npy")
    path = next(snapshot / (stem + s) for s in SUFFIXES if (snapshot / (stem + s)).is_file())
    if path.name.endswith(".zlib"):
        return unpack(path.read_bytes(), str(path), delta=path.name.endswith(DELTA_PACKED))
    return np.load(path, allow_pickle=False)


def test_format_4_stores_narrow_columns_and_no_derived_points(tmp_path, rich_state):
    """OpenCV's keypoints are float32 values, levels fit int8, ids int32, and every point is
    its landmark's: so none of them costs its full width on disk, and all load back exactly;
    landmark points are float32 offsets from their anchor keyframes."""
    snap = save_map(rich_state, tmp_path)
    manifest = json.loads((snap / "manifest.json").read_text())
    assert manifest["format_version"] == storage.UNSHARED_FORMAT_VERSION  # format 4's and more
    for kind in ("sift", "orb"):
        for derived in ("points_world", "landmark_ids"):
            assert f"features/{kind}.{derived}.npy" not in manifest["files"]
            assert not (snap / "features" / f"{kind}.{derived}.npy").exists()
        assert _snapshot_npy(snap, f"features/{kind}.levels.npy").dtype == np.int8
    assert _snapshot_npy(snap, "features/sift.keypoints_px.npy").dtype == np.float32
    # ORB's keypoints are integer pixels of their level times its scale: int16 and a table
    assert not (snap / "features" / "orb.keypoints_px.npy").exists()
    assert _snapshot_npy(snap, "features/orb.keypoints_level_px.npy").dtype == np.int16
    assert _snapshot_npy(snap, "features/orb.keypoint_scales_by_level.npy").shape == (8, 2)
    # ORB's angles: read by nothing after extraction, not saved, loaded as OpenCV's "none"
    assert not (snap / "features" / "orb.angles.npy").exists()
    assert (snap / "features" / "sift.angles.npy").is_file()
    landmark_dtypes = {"obs_offsets": np.int32, "obs_keyframe": np.int16, "obs_kind": np.int8,
                       "obs_keypoint": np.int16, "ids": np.int32, "anchored_points_world":
                       np.float32, "depth_sigmas_m": np.float32}
    assert not (snap / "landmarks" / "points_world.npy").exists()
    for name, dtype in landmark_dtypes.items():
        assert _snapshot_npy(snap, f"landmarks/{name}.npy").dtype == dtype, name
    # ORB's size is its level's (31 px times the scale); SIFT's varies within an octave
    table = _snapshot_npy(snap, "features/orb.sizes_by_level.npy")
    assert table.dtype == np.float32 and table.shape == (8, 2)
    assert not (snap / "features" / "orb.sizes.npy").exists()
    assert (snap / "features" / "sift.sizes.npy").is_file()
    state, _ = load_map(tmp_path)
    _assert_states_equal(rich_state, state)
    assert np.all(state.keyframes[1].features["orb"].angles == -1.0)
    assert np.any(rich_state.keyframes[1].features["orb"].angles != -1.0)
    feats = state.keyframes[1].features["sift"]
    has = feats.landmark_ids >= 0
    assert has.any() and np.isnan(feats.points_world[~has]).all()
    assert np.array_equal(feats.points_world[has], state.landmarks.points(feats.landmark_ids[has]))


def test_points_that_are_not_the_landmarks_are_stored(tmp_path, synthetic_map):
    """A client may give a keypoint a point other than its landmark's: that kind keeps its
    points column, and the round trip stays exact."""
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    kf = synthetic_map.keyframes[1]
    feats = kf.features["sift"]
    i = int(np.flatnonzero(feats.landmark_ids >= 0)[0])
    moved = feats.with_landmarks([i], feats.landmark_ids[[i]], feats.points_world[[i]] + 0.5)
    kmap.add_keyframe(kf.with_features("sift", moved))
    state = kmap.snapshot()
    snap = save_map(state, tmp_path)
    assert (snap / "features" / "sift.points_world.npy").is_file()
    loaded, _ = load_map(tmp_path)
    _assert_states_equal(state, loaded)
    assert np.array_equal(loaded.keyframes[1].features["sift"].points_world[i],
                          feats.points_world[i] + 0.5)


def test_orb_keypoints_off_their_level_grid_stay_float32(tmp_path, rich_state):
    """A client's keypoints (described where given) are not level pixels times a scale: that
    map keeps the float32 column, exactly."""
    from reloc_service.core.features import compute_at

    kmap = KeyframeMap()
    kmap.replace_state(rich_state)
    kf = rich_state.keyframes[1]
    given, _ = compute_at(kf.image, "orb", kf.features["orb"].keypoints_px[:50] + 0.25)
    kmap.add_keyframe(kf.with_features("orb", given))
    snap = save_map(kmap.snapshot(), tmp_path)
    assert _snapshot_npy(snap, "features/orb.keypoints_px.npy").dtype == np.float32
    assert not (snap / "features" / "orb.keypoints_level_px.npy").exists()
    _assert_states_equal(kmap.snapshot(), load_map(tmp_path)[0])


def test_keypoints_that_are_not_float32_values_stay_float64(tmp_path, synthetic_map):
    from reloc_service.core.frame import Features

    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    kf = synthetic_map.keyframes[0]
    f = kf.features["sift"]
    exact = Features(**{**{n: getattr(f, n) for n in FEATURE_FIELDS}, "kind": "sift",
                        "keypoints_px": f.keypoints_px + 1e-9})
    kmap.add_keyframe(kf.with_features("sift", exact))
    snap = save_map(kmap.snapshot(), tmp_path)
    assert _snapshot_npy(snap, "features/sift.keypoints_px.npy").dtype == np.float64
    _assert_states_equal(kmap.snapshot(), load_map(tmp_path)[0])


@pytest.mark.parametrize("rel", ["features/sift.keypoints_px.npy", "features/orb.sizes_by_level.npy",
                                 "features/orb.keypoints_level_px.npy",
                                 "features/orb.keypoint_scales_by_level.npy",
                                 "features/sift.descriptors.npy"])
def test_a_flipped_bit_in_a_format_3_column_fails_the_load(tmp_path, rich_state, rel):
    snap = save_map(rich_state, tmp_path)
    path = snap / rel
    data = bytearray(path.read_bytes())
    data[-3] ^= 0x04
    path.write_bytes(bytes(data))
    with pytest.raises(StorageError, match=f"{rel}: checksum mismatch"):
        load_map(tmp_path)


def test_format_2_snapshots_are_read(tmp_path):
    """A snapshot written by format 2 (made by that version's code from the format-1 fixture,
    plus keyframe 1's ORB features: none in its 32x24 image, an empty kind, and the small
    blurry images; kept in tests/data) loads as it was, and saves as the current format."""
    v1, _ = load_map(V1_MAP)
    state, models = load_map(V2_MAP)
    assert models is None and state.keyframe_ids() == [0, 1]
    assert sorted(state.keyframes[1].features) == ["orb", "sift"]
    assert len(state.keyframes[1].features["orb"]) == 0
    assert state.keyframes[1].features["orb"].descriptors.shape == (0, 32)
    for k in (0, 1):
        for name in FEATURE_FIELDS:
            a = getattr(v1.keyframes[k].features["sift"], name)
            b = getattr(state.keyframes[k].features["sift"], name)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name
        assert "sbi:40x30:2.5" in state.keyframes[k].cache
    assert sorted(state.landmarks) == sorted(v1.landmarks)
    snap = save_map(state, tmp_path)
    manifest = json.loads((snap / "manifest.json").read_text())
    assert manifest["format_version"] == storage.UNSHARED_FORMAT_VERSION
    again, _ = load_map(tmp_path)
    _assert_states_equal(state, again)


V3_MAP = Path(__file__).parent / "data" / "map_v3"


def test_format_3_snapshots_are_read(tmp_path):
    """A snapshot written by format 3 (made by that version's code from the format-2 fixture:
    float64 landmark points, int64 ids; kept in tests/data) loads as the format-2 one, and
    saves as the current format."""
    manifest = json.loads((V3_MAP / "snapshots" / "000001" / "manifest.json").read_text())
    assert manifest["format_version"] == 3
    v2, _ = load_map(V2_MAP)
    state, _ = load_map(V3_MAP)
    _assert_states_equal(v2, state)
    assert np.array_equal(state.landmark_points(sorted(v2.landmarks)),
                          v2.landmark_points(sorted(v2.landmarks)))
    # written before keyframes had a pose covariance: none, the map's default applies
    assert all(kf.pose_covariance is None for kf in state.keyframes.values())
    snap = save_map(state, tmp_path)
    manifest = json.loads((snap / "manifest.json").read_text())
    assert manifest["format_version"] == storage.UNSHARED_FORMAT_VERSION
    _assert_states_equal(state, load_map(tmp_path)[0])


def test_saving_a_loaded_map_copies_its_columns_without_building_features(tmp_path, rich_state):
    save_map(rich_state, tmp_path / "a")
    state, _ = load_map(tmp_path / "a")
    snap = save_map(state, tmp_path / "b")
    assert all("built=[]" in repr(kf.features) for kf in state.keyframes.values())
    first = current_snapshot(tmp_path / "a")
    for path in sorted((first / "features").iterdir()):
        assert (snap / "features" / path.name).read_bytes() == path.read_bytes(), path.name
    # rounding happens once: the loaded float32 landmark geometry saves to the same bytes
    for path in sorted((first / "landmarks").iterdir()):
        assert (snap / "landmarks" / path.name).read_bytes() == path.read_bytes(), path.name
    assert (first / "landmarks" / "anchored_points_world.npy").is_file()
    _assert_states_equal(rich_state, load_map(tmp_path / "b")[0])


def test_a_keyframe_sent_as_jpeg_is_saved_as_those_bytes(tmp_path, synthetic_scene):
    """The map keeps the JPEG a client sent (a third of a PNG of its pixels): the file saved
    is those bytes, and its pixels and features load back exactly."""
    import cv2

    from reloc_service.core.mapping import MapBuilder

    image = synthetic_scene.keyframe_images[0]
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    sent = EncodedImage(buf.tobytes(), image.shape)
    kmap = KeyframeMap()
    kf = MapBuilder(kmap).add_keyframe(3, sent, synthetic_scene.camera,
                                       synthetic_scene.keyframe_poses[0])
    assert kf.encoded is sent and np.array_equal(kf.image, cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))
    snap = save_map(kmap.snapshot(), tmp_path)
    assert (snap / "images" / "3.jpg").read_bytes() == buf.tobytes()
    assert not (snap / "images" / "3.png").exists()
    state, _ = load_map(tmp_path)
    _assert_states_equal(kmap.snapshot(), state)
    again = save_map(state, tmp_path)                     # never re-encoded
    assert (again / "images" / "3.jpg").read_bytes() == buf.tobytes()


def test_an_encoded_image_must_match_its_pixels(synthetic_scene):
    import cv2

    from reloc_service.core.errors import GeometryError

    image = synthetic_scene.keyframe_images[0]
    ok, buf = cv2.imencode(".jpg", image[:100])
    with pytest.raises(GeometryError, match="encoded image"):
        Keyframe(image=image, camera=synthetic_scene.camera, id=1,
                 encoded=EncodedImage(buf.tobytes(), (100, image.shape[1])))
    with pytest.raises(GeometryError, match="a JPEG file and its"):
        EncodedImage(buf.tobytes())


def test_ids_the_observations_do_not_give_are_stored(tmp_path, synthetic_map):
    """A keypoint naming a landmark that does not list it as an observation (the ids are not
    the observations' inverse): the ids column is kept, and the round trip stays exact."""
    from types import MappingProxyType

    kf = synthetic_map.keyframes[0]
    feats = kf.features["sift"]
    free = int(np.flatnonzero(feats.landmark_ids < 0)[0])
    lm = next(iter(synthetic_map.landmarks.values()))
    odd = feats.with_landmarks([free], [lm.id], [lm.point_world])
    state = MapState(MappingProxyType({**synthetic_map.keyframes, 0: kf.with_features("sift", odd)}),
                     synthetic_map.landmarks, synthetic_map.version, synthetic_map.next_landmark_id)
    snap = save_map(state, tmp_path)
    assert (snap / "features" / "sift.landmark_ids.npy").is_file()
    assert not (snap / "features" / "sift.points_world.npy").exists()
    loaded, _ = load_map(tmp_path)
    _assert_states_equal(state, loaded)
    assert loaded.keyframes[0].features["sift"].landmark_ids[free] == lm.id


def test_exact_geometry_saves_landmarks_as_held(tmp_path, synthetic_map):
    """``exact_geometry`` (the snapshot a service's worker processes load) keeps float64
    points and sigmas, so a replica's landmarks are the map's bit for bit; by default the
    same map is stored as float32 offsets, and loads back only approximately."""
    state = synthetic_map
    snap = save_map(state, tmp_path / "exact", exact_geometry=True)
    assert _snapshot_npy(snap, "landmarks/points_world.npy").dtype == np.float64
    assert not (snap / "landmarks" / "anchored_points_world.npy").exists()
    ids = state.landmarks.id_array()
    exact, _ = load_map(tmp_path / "exact")
    assert np.array_equal(exact.landmark_points(ids), state.landmark_points(ids))
    save_map(state, tmp_path / "compact")
    compact, _ = load_map(tmp_path / "compact")
    assert not np.array_equal(compact.landmark_points(ids), state.landmark_points(ids))


def test_a_map_of_more_keyframes_than_open_files_allowed_loads(tmp_path, synthetic_map):
    """Every keyframe image stays mapped, yet no file stays open per keyframe: a map of 200
    keyframes loads, every image readable, in a process allowed 128 open files (systemd's
    default soft limit is 1024, and maps of thousands of keyframes are common). 200 is past
    the limit with room to spare: a file kept open per image fails the load, and one per
    two images leaves more than 64 open after it (each PNG written costs a few ms)."""
    first = synthetic_map.keyframes[synthetic_map.keyframe_ids()[0]]
    kmap = KeyframeMap()
    for i in range(200):
        kmap.add_keyframe(Keyframe(image=first.image, camera=first.camera, id=i,
                                   world_from_cam=first.world_from_cam, features={}))
    save_map(kmap.snapshot(), tmp_path)
    code = textwrap.dedent(f"""
        import os, resource
        resource.setrlimit(resource.RLIMIT_NOFILE,
                           (128, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
        from reloc_service.storage.snapshot import load_map
        state, _ = load_map({str(tmp_path)!r})
        images = [kf.image for kf in state.keyframes.values()]
        assert len(images) == 200 and all(im.shape == images[0].shape for im in images)
        print(len(os.listdir("/proc/self/fd")))
    """)
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True,
                          text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{root / 'clients'}"})
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[-1]) < 64  # open files after the load: not one per image


def test_a_loaded_map_keeps_no_file_open(tmp_path, synthetic_map):
    """Neither the keyframe images nor the feature and landmark arrays (.npy, memory-mapped)
    keep a file open once loaded: ten copies of a map loaded side by side hold no more open
    files than none (np.load's memory maps kept one per array, about ten per map), and
    their arrays read as saved."""
    import os

    state = synthetic_map.snapshot() if hasattr(synthetic_map, "snapshot") else synthetic_map
    save_map(state, tmp_path)
    before = len(os.listdir("/proc/self/fd"))
    loaded = [load_map(tmp_path)[0] for _ in range(10)]
    held = len(os.listdir("/proc/self/fd")) - before
    assert held <= 2, f"{held} more open files after loading the map 10 times"
    assert any(kf.features for kf in state.keyframes.values())
    for copy in loaded:
        assert sorted(copy.keyframes) == sorted(state.keyframes)
        for kf_id, kf in state.keyframes.items():
            for kind, feats in kf.features.items():
                got = copy.keyframes[kf_id].features[kind]
                assert np.array_equal(got.keypoints_px, feats.keypoints_px)
                assert np.array_equal(got.descriptors, feats.descriptors)


def test_a_save_failing_on_a_full_disk_removes_its_partial_snapshot(tmp_path, synthetic_map,
                                                                   monkeypatch):
    """Injected: a keyframe image's write puts half its bytes on disk, then raises ENOSPC.
    The partial snapshot directory is removed (its space given back), CURRENT is unchanged."""
    import errno
    import os

    first = _tiny_state(synthetic_map, 2)
    kept = save_map(first, tmp_path)
    real_write = snapshot_files.SnapshotWriter.write

    def full_disk(self, relpath, data):
        if relpath.startswith("images/"):
            (self.root / relpath).parent.mkdir(parents=True, exist_ok=True)
            (self.root / relpath).write_bytes(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(self, relpath, data)

    monkeypatch.setattr(snapshot_files.SnapshotWriter, "write", full_disk)
    with pytest.raises(OSError) as err:
        save_map(synthetic_map, tmp_path)
    assert err.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert [p.name for p in (tmp_path / "snapshots").iterdir()] == [kept.name]
    assert current_snapshot(tmp_path) == kept
    _assert_states_equal(first, load_map(tmp_path)[0])
