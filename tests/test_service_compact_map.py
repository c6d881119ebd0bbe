"""A real service process keeps a compact map: after a clean stop its snapshot holds no depth
map and no keyframe image (its methods read neither), and the restarted map answers as before."""
# ruff: noqa: E402

from __future__ import annotations

import json

import numpy as np
import pytest
from reloc_client.client import ServiceError
from service_support import MAP, Events, ServiceProcess, free_port, write_config

from reloc_service.core.geometry import pose_error
from reloc_service.storage.snapshot_files import current_snapshot


@pytest.mark.slow   # a service mapping every keyframe, stopped and restarted: over a minute
def test_a_clean_stop_leaves_a_map_without_depth_or_images_that_answers_alike(
        synthetic_scene, tmp_path):
    port = free_port()
    config = write_config(tmp_path, port, snapshot_every=0, methods=["sbi+p3p"],
                          default_method="sbi+p3p")
    scene = synthetic_scene
    service = ServiceProcess(config, port, tmp_path / "log1.txt")
    try:
        events = Events(service.client)
        service.client.set_camera("cam0", scene.camera)
        for kf_id in range(len(scene.keyframe_images)):
            service.client.add_keyframe(kf_id, scene.keyframe_images[kf_id],
                                        scene.keyframe_poses[kf_id], camera_id="cam0",
                                        depth=scene.keyframe_depths[kf_id])
        events.wait("keyframe_added", id=len(scene.keyframe_images) - 1)
        before = service.client.relocalize(scene.query_images[1], camera_id="cam0")
    finally:
        assert service.terminate() == 0
    assert before.ok
    snapshot = current_snapshot(tmp_path / "storage" / MAP / "map")
    files = json.loads((snapshot / "manifest.json").read_text())["files"]
    assert files and not [f for f in files if f.startswith(("depth/", "images/"))]
    # what the depth maps alone took before: 4 bytes a pixel, each keyframe
    raw_depth = sum(d.nbytes for d in scene.keyframe_depths)
    on_disk = sum(p.stat().st_size for p in (tmp_path / "storage").rglob("*") if p.is_file())
    assert on_disk < raw_depth
    restarted = ServiceProcess(config, port, tmp_path / "log2.txt")
    try:
        after = restarted.client.relocalize(scene.query_images[1], camera_id="cam0")
        with pytest.raises(ServiceError) as refused:   # a peer cannot copy the pixels
            restarted.client.keyframes(images=True)
    finally:
        assert restarted.terminate() == 0
    assert 'keyframe_images = "always"' in str(refused.value)
    assert after.ok and after.world_from_cam is not None and before.world_from_cam is not None
    dt, dr = pose_error(after.world_from_cam, before.world_from_cam)
    assert dt < 1e-3 and np.degrees(dr) < 0.05
