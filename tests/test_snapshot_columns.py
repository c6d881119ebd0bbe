"""Snapshot columns (format 3 and later): narrow dtypes, points derived at load instead of
stored, images kept as sent, damaged columns named, older formats read; and saves and loads at
the edges: ids the observations do not give, more keyframes than open files allowed, no file
kept open, a full disk."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from map_state_support import assert_states_equal, enriched_state, tiny_state
from stored_maps import stored_map

from reloc_service.core.errors import StorageError
from reloc_service.core.frame import EncodedImage, Keyframe
from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.storage import snapshot as storage
from reloc_service.storage import snapshot_files
from reloc_service.storage.snapshot import (
    FEATURE_FIELDS,
    current_snapshot,
    load_map,
    save_map,
)


@pytest.fixture(scope="module")
def rich_state(synthetic_scene, synthetic_map) -> MapState:
    """The synthetic map with a depth map, a timestamp-less keyframe and ORB features too."""
    return enriched_state(synthetic_scene, synthetic_map)


# -- format 3: narrow columns, derived points, images as sent ---------------------------------

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
    # angles: read by nothing after extraction, not saved, loaded as OpenCV's "none"
    assert not (snap / "features" / "orb.angles.npy").exists()
    assert not (snap / "features" / "sift.angles.npy").exists()
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
    assert_states_equal(rich_state, state)
    for kind in ("orb", "sift"):
        assert np.all(state.keyframes[1].features[kind].angles == -1.0)
        assert np.any(rich_state.keyframes[1].features[kind].angles != -1.0)
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
    assert_states_equal(state, loaded)
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
    assert_states_equal(kmap.snapshot(), load_map(tmp_path)[0])


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
    assert_states_equal(kmap.snapshot(), load_map(tmp_path)[0])


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
    v1, _ = load_map(stored_map(1))
    state, models = load_map(stored_map(2))
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
    assert_states_equal(state, again)



def test_format_3_snapshots_are_read(tmp_path):
    """A snapshot written by format 3 (made by that version's code from the format-2 fixture:
    float64 landmark points, int64 ids; kept in tests/data) loads as the format-2 one, and
    saves as the current format."""
    manifest = json.loads((stored_map(3) / "snapshots" / "000001" / "manifest.json").read_text())
    assert manifest["format_version"] == 3
    v2, _ = load_map(stored_map(2))
    state, _ = load_map(stored_map(3))
    assert_states_equal(v2, state)
    assert np.array_equal(state.landmark_points(sorted(v2.landmarks)),
                          v2.landmark_points(sorted(v2.landmarks)))
    # written before keyframes had a pose covariance: none, the map's default applies
    assert all(kf.pose_covariance is None for kf in state.keyframes.values())
    snap = save_map(state, tmp_path)
    manifest = json.loads((snap / "manifest.json").read_text())
    assert manifest["format_version"] == storage.UNSHARED_FORMAT_VERSION
    assert_states_equal(state, load_map(tmp_path)[0])


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
    assert_states_equal(rich_state, load_map(tmp_path / "b")[0])


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
    assert_states_equal(kmap.snapshot(), state)
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
    assert_states_equal(state, loaded)
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

    first = tiny_state(synthetic_map, 2)
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
    assert_states_equal(first, load_map(tmp_path)[0])
