"""What the tests of a service with a memory budget (``[service] max_resident_mb``) share:
its configuration, a stored map of the synthetic scene, copies of it, a pose asked of it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from reloc_client.client import RelocClient
from service_support import service_conf

from reloc_service.engine import EngineConf
from reloc_service.service.config import ServiceConf
from reloc_service.tools.bench.stored_map import (
    StoredMap,
    copy_map,
    engine_from_images,
    stored_template,
)

METHOD = "sbi+p3p"
NAMES = ("alpha", "bravo", "charlie")


def conf(port: int, storage: Path, **service) -> ServiceConf:
    return service_conf(port, storage, **{"methods": [METHOD], "default_method": METHOD,
                                          "worker_mode": "thread", "workers": 2,
                                          "snapshot_every": 0, **service})


def scene_template(scene, storage: Path) -> StoredMap:
    """A stored map in ``storage`` (camera cam0, the scene's 6 keyframes, trained, in a
    snapshot) and the bytes it counts once loaded from its snapshot (its quota usage)."""
    engine = engine_from_images(scene.camera, scene.keyframe_images, scene.keyframe_poses,
                                EngineConf(methods=(METHOD,)))
    return stored_template(storage, "template", engine)


def stored_maps(template: StoredMap, storage: Path, names=NAMES) -> Path:
    """``storage`` holding a copy of the template map under each of ``names``."""
    for name in names:
        copy_map(template, storage, name)
    return storage


def pose_of(client: RelocClient, scene, i: int) -> np.ndarray:
    result = client.relocalize(scene.query_images[i], camera_id="cam0")
    assert result.ok, result.reason
    return np.asarray(result.world_from_cam)
