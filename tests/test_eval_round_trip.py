"""``reloc eval --round-trip``: the map queried is the one a service restores from its
snapshot (compact by default), not the one built in memory."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest

from reloc_service.cli import main as cli_main
from reloc_service.core.errors import ConfigError
from reloc_service.core.landmark_rows import holds_landmark_rows_only
from reloc_service.storage.feature_columns import LazyFeatures
from reloc_service.storage.landmark_codec import ANCHORED_POINTS
from reloc_service.storage.landmark_descriptors import SHARED_DESCRIPTORS
from reloc_service.storage.snapshot_files import current_snapshot
from reloc_service.tools.eval.backends import LandmarkSource
from reloc_service.tools.eval.inprocess import InProcessBackend


def _trained(scene, options) -> InProcessBackend:
    backend = InProcessBackend(["sbi+p3p"], options, LandmarkSource.TRIANGULATE)
    for i, (image, pose) in enumerate(zip(scene.keyframe_images, scene.keyframe_poses,
                                          strict=True)):
        backend.add_keyframe(i, image, scene.camera, pose, depth=None)
    backend.train(progress=False)
    return backend


def test_a_round_trip_queries_the_map_loaded_from_a_default_snapshot(synthetic_scene):
    scene = synthetic_scene
    backend = _trained(scene, {})
    built = backend.engine
    backend.round_trip()
    try:
        assert backend.engine is not built
        state = backend.engine.map.snapshot()
        kf = state.keyframes[0]
        assert isinstance(kf.features, LazyFeatures)       # read from the snapshot's columns
        assert holds_landmark_rows_only(kf)                 # the service's default: landmark rows
        assert np.all(kf.features["sift"].landmark_ids >= 0)
        result = backend.relocalize(scene.query_images[1], scene.camera, method="sbi+p3p",
                                    gt_world_from_cam=scene.query_poses[1])
        assert result.ok
        assert np.linalg.norm(result.world_from_cam[:3, 3] - scene.query_poses[1][:3, 3]) < 0.05
    finally:
        backend.close()


def test_a_round_trip_through_a_remote_service_is_a_usage_error(capsys):
    assert cli_main.main(["eval", "somewhere", "--remote", "tcp/127.0.0.1:1", "--map", "m",
                          "--round-trip"]) == 2
    assert "--round-trip evaluates in-process" in capsys.readouterr().err


def test_a_round_trip_stores_what_the_service_table_of_the_options_says(synthetic_scene):
    backend = _trained(synthetic_scene, {"service": {"keyframe_descriptors": "per-landmark"}})
    try:
        backend.round_trip()
        assert backend._snapshot_dir is not None
        snap = current_snapshot(Path(backend._snapshot_dir.name))
        files = json.loads((snap / "manifest.json").read_text())["files"]
        assert f"features/sift.{SHARED_DESCRIPTORS}.npy" in files
        assert "features/sift.descriptors.npy" not in files
    finally:
        backend.close()


def test_compact_centres_and_points_round_trip_to_the_same_answers(synthetic_scene):
    """``vocabulary_centres = "uint8"``, ``landmark_points = "float16"``: the snapshot holds
    uint8 vocabulary centres and float16 points (format 10); the map restored from it
    answers within 5 cm, and saved and restored again answers the same, to the last digit."""
    options = {"service": {"vocabulary_centres": "uint8", "landmark_points": "float16"}}
    backend = InProcessBackend(["bow+p3p"], options, LandmarkSource.TRIANGULATE)
    scene = synthetic_scene
    try:
        for i, (image, pose) in enumerate(zip(scene.keyframe_images, scene.keyframe_poses,
                                              strict=True)):
            backend.add_keyframe(i, image, scene.camera, pose, depth=None)
        backend.train(progress=False)
        answers = []
        for _ in range(2):
            backend.round_trip()
            assert backend._snapshot_dir is not None
            snap = current_snapshot(Path(backend._snapshot_dir.name))
            manifest = json.loads((snap / "manifest.json").read_text())
            assert manifest["format_version"] == 10
            assert np.load(snap / f"landmarks/{ANCHORED_POINTS}.npy").dtype == np.float16
            (model,) = snap.glob("models/*/place_bow.msgpack.zlib")
            state = msgpack.unpackb(zlib.decompress(model.read_bytes()), raw=False)
            assert state["tree"]["stored_dtype"] == "uint8"
            result = backend.relocalize(scene.query_images[1], scene.camera, method="bow+p3p",
                                        gt_world_from_cam=scene.query_poses[1])
            assert result.ok
            assert np.linalg.norm(result.world_from_cam[:3, 3] - scene.query_poses[1][:3, 3]) < 0.05
            answers.append(result.world_from_cam)
        assert np.array_equal(answers[0], answers[1])
    finally:
        backend.close()


def test_an_unknown_service_option_is_refused_by_name_before_a_map_is_built():
    with pytest.raises(ConfigError, match=r"options: \[service\]: unknown option\(s\) "
                                          r"\['keyframe_descriptor'\]"):
        InProcessBackend(["sbi+p3p"], {"service": {"keyframe_descriptor": "per-landmark"}},
                         LandmarkSource.TRIANGULATE)
