"""The service the API tests share: map ``lab`` uploaded over real Zenoh on loopback and served
by the real ``sbi+p3p`` (test_service_api.py, test_service_malformed.py)."""

from __future__ import annotations

import math

import numpy as np
from reloc_client.client import RelocClient
from service_support import Events, endpoint, free_port, service_conf

from reloc_service.core.geometry import pose_error
from reloc_service.service.app import Service

MAP = "lab"
METHOD = "sbi+p3p"
MAX_T_ERR_M = 0.05
MAX_R_ERR_RAD = math.radians(2.0)


def assert_pose(world_from_cam: np.ndarray, gt: np.ndarray) -> None:
    dt, dr = pose_error(world_from_cam, gt)
    assert dt < MAX_T_ERR_M and dr < MAX_R_ERR_RAD, (dt, math.degrees(dr))


def upload(client: RelocClient, scene, events: Events, *, ids=None, camera_id="cam0") -> None:
    client.set_camera(camera_id, scene.camera)
    events.wait("camera_added", id=camera_id)
    ids = list(range(len(scene.keyframe_images))) if ids is None else ids
    for kf_id, image, pose in zip(ids, scene.keyframe_images, scene.keyframe_poses, strict=False):
        client.add_keyframe(kf_id, image, pose, camera_id=camera_id, timestamp=float(kf_id))
    for kf_id in ids:
        events.wait("keyframe_added", id=kf_id)


def served_api(synthetic_scene, tmp_path_factory):
    """A service (2 workers, 2 queue slots, small limits) with map ``lab`` uploaded."""
    port = free_port()
    storage = tmp_path_factory.mktemp("storage")
    conf = service_conf(port, storage, maps=("empty",), queue_size=2,
                        methods=[METHOD, "bow+p3p"], default_method=METHOD,
                        train_on_load=False,
                        limits={"max_payload_bytes": 2_000_000, "max_image_pixels": 640 * 480})
    service = Service(conf).start()
    client = RelocClient(endpoint(port), map=MAP, timeout=30)
    events = Events(client)
    upload(client, synthetic_scene, events)
    yield service, port, client, events
    events.close()
    client.close()
    service.stop()
