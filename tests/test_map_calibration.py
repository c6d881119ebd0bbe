"""A map's own calibration accuracy (``[maps.NAME] calibration_focal_sigma_rel`` /
``calibration_radial_sigma_px``), on loopback with real Zenoh: two maps of the same scene
stating different accuracies answer every query with the same pose, the looser one with a
covariance at least as wide (wider where the calibration matters), in both worker modes; each
map's status says what it states; a bad value is refused at start naming the map and key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from reloc_client import protocol as wire
from reloc_client.client import RelocClient
from service_support import endpoint, free_port, raw_session, wait_until

from reloc_service.algorithms.relocalizers.base import position_sigma_m
from reloc_service.core.errors import ConfigError
from reloc_service.engine import EngineConf
from reloc_service.service.app import Service
from reloc_service.service.config import load_config, parse_config
from reloc_service.tools.bench.stored_map import copy_map, engine_from_images, stored_template

pytest.importorskip("reloc_service.algorithms.pose.p3p")

#: The service-wide calibration is stated exact and keyframe poses exact, so the covariance
#: of "exact" is the landmarks' alone and "loose" adds its calibration's part.
MAPS = {"exact": {}, "loose": {"calibration_focal_sigma_rel": 0.02,
                               "calibration_radial_sigma_px": 4.0}}
MAPPING = {"keyframe_position_sigma_m": 0.0, "keyframe_rotation_sigma_deg": 0.0,
           "calibration_focal_sigma_rel": 0.0, "calibration_radial_sigma_px": 0.0}


def _conf(port: int, worker_mode: str):
    return parse_config({
        "zenoh": {"mode": "peer", "listen": [endpoint(port)], "multicast_scouting": False},
        "service": {"instance": "test", "storage": "", "workers": 1,
                    "worker_mode": worker_mode, "methods": ["sbi+p3p"],
                    "default_method": "sbi+p3p"},
        "maps": MAPS, "mapping": MAPPING})


def _serve(port: int, worker_mode: str, scene) -> Service:
    """A service holding both maps, each built from the same puts of the scene."""
    service = Service(_conf(port, worker_mode)).start()
    camera = wire.CameraPut("cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode()
    for name in MAPS:
        service.on_camera_sample(name, "cam0", camera)
        for kf_id, (image, pose) in enumerate(zip(scene.keyframe_images, scene.keyframe_poses,
                                                  strict=True)):
            service.on_keyframe_sample(name, kf_id, wire.KeyframePut(
                id=kf_id, image=wire.WireImage.from_array(image),
                world_from_cam=wire.WirePose.from_matrix(pose), camera_id="cam0").encode())
    assert service.wait_idle(60)
    if worker_mode == "process":   # the queries below go to the workers' replicas
        assert service.processes is not None
        service.start_workers_in_background()
        wait_until(lambda: all(service.processes.replica_ready(n) for n in MAPS), timeout=60)
    return service


def _answers(port: int, name: str, scene) -> list[wire.RelocalizeReply]:
    """Each query image's reply from map ``name``, over Zenoh."""
    requests = [wire.RelocalizeRequest(image=wire.WireImage.from_array(image),
                                       camera_id="cam0", request_id=f"q{i}")
                for i, image in enumerate(scene.query_images)]
    replies = []
    with raw_session(port) as session:
        for request in requests:
            (reply,) = list(session.get(wire.keys.relocalize("reloc", name),
                                        payload=request.encode(), timeout=60))
            assert reply.ok is not None, reply.err.payload.to_bytes()
            replies.append(wire.RelocalizeReply.decode(reply.ok.payload.to_bytes()))
    return replies


@pytest.mark.parametrize("worker_mode", ["thread", "process"])
def test_a_looser_map_states_a_wider_covariance_for_the_same_pose(synthetic_scene,
                                                                   worker_mode):
    """Two maps of the same scene, one stating its calibration exact, one loose: every query
    gets the same answer from both, the loose map's covariance contains the exact one's and
    is wider where the calibration matters; each map's status says what it states."""
    port = free_port()
    service = _serve(port, worker_mode, synthetic_scene)
    try:
        exact, loose = (_answers(port, name, synthetic_scene) for name in MAPS)
        if worker_mode == "process":   # the replicas answered, not the service
            assert not any(service.maps[n].stats.counters.get("relocalize_in_service", 0)
                           for n in MAPS)
        wider = 0
        for a, b in zip(exact, loose, strict=True):
            assert (a.status, a.inliers, a.method) == (b.status, b.inliers, b.method)
            if a.world_from_cam is None:
                continue
            assert b.world_from_cam is not None
            np.testing.assert_array_equal(a.world_from_cam.matrix(), b.world_from_cam.matrix())
            assert a.covariance is not None and b.covariance is not None
            ca, cb = (np.reshape(c.covariance, (6, 6)) for c in (a, b))
            assert np.linalg.eigvalsh(cb - ca).min() > -1e-12
            wider += position_sigma_m(cb) > 1.05 * position_sigma_m(ca)
        assert sum(a.world_from_cam is not None for a in exact) >= 2
        assert wider >= 1
        with RelocClient(endpoint(port), map="loose", timeout=30) as client:
            assert client.status().calibration_sigma == {"focal_rel": 0.02, "radial_px": 4.0}
        with RelocClient(endpoint(port), map="exact", timeout=30) as client:
            assert client.status().calibration_sigma == {}   # the service-wide [mapping]
    finally:
        service.stop(final_snapshot=False)


@pytest.mark.parametrize(("value", "expected"), [
    ("-0.01", "expected a finite number >= 0"), ("nan", "expected a finite number >= 0"),
    ('"2%"', "expected float"), ("true", "expected float")])
def test_a_bad_map_calibration_is_refused_at_start_naming_the_map(tmp_path: Path, value,
                                                                   expected):
    path = tmp_path / "reloc.toml"
    path.write_text(f"[maps.phone]\ncalibration_focal_sigma_rel = {value}\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=expected) as info:
        load_config(path)
    assert "[maps.phone].calibration_focal_sigma_rel" in str(info.value)


def test_a_map_without_its_own_calibration_takes_the_service_wide_one():
    conf = parse_config({"mapping": {"calibration_radial_sigma_px": 1.0, "neighbours": 3},
                         "maps": {"drone": {"calibration_focal_sigma_rel": 0.001},
                                  "lab": {}}})
    assert dict(conf.mapping_for("drone")) == {"calibration_radial_sigma_px": 1.0,
                                               "neighbours": 3,
                                               "calibration_focal_sigma_rel": 0.001}
    assert dict(conf.mapping_for("lab")) == dict(conf.mapping_for("created-by-a-put")) == {
        "calibration_radial_sigma_px": 1.0, "neighbours": 3}


def test_a_stored_map_states_its_own_calibration_before_and_after_it_loads(synthetic_scene,
                                                                           tmp_path):
    """With ``max_resident_mb``, a stored map's status before its first use (not loaded)
    and after it (its engine built with the map's own configuration) says the same
    calibration accuracy; the query it loads for states the covariance of that accuracy."""
    template = stored_template(tmp_path / "template", "template", engine_from_images(
        synthetic_scene.camera, synthetic_scene.keyframe_images, synthetic_scene.keyframe_poses,
        EngineConf(methods=("sbi+p3p",))))
    storage = tmp_path / "storage"
    copy_map(template, storage, "loose")
    port = free_port()
    conf = parse_config({
        "zenoh": {"mode": "peer", "listen": [endpoint(port)], "multicast_scouting": False},
        "service": {"instance": "test", "storage": str(storage), "worker_mode": "thread",
                    "methods": ["sbi+p3p"], "default_method": "sbi+p3p",
                    "max_resident_mb": 1_000_000},
        "maps": {"loose": MAPS["loose"]}, "mapping": MAPPING})
    service = Service(conf).start()
    try:
        with RelocClient(endpoint(port), map="loose", timeout=30) as client:
            before = client.status()
            assert not before.resident
            assert before.calibration_sigma == {"focal_rel": 0.02, "radial_px": 4.0}
            assert client.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok
            after = client.status()
            assert after.resident and after.calibration_sigma == before.calibration_sigma
        mapping = service.maps["loose"].engine.conf.mapping
        assert (mapping.calibration_focal_sigma_rel, mapping.calibration_radial_sigma_px) == (
            0.02, 4.0)
    finally:
        service.stop(final_snapshot=False)
