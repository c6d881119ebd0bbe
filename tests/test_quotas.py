"""Quotas with clear refusals, on real Zenoh sessions over loopback: the map after the maximum,
the keyframe after a map's maximum (freed by a delete), bytes per map and in total (counted
again after a restart), and the memory of refused oversized puts given back."""
# ruff: noqa: E402

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import pytest
import zenoh
from reloc_client import protocol as wire
from reloc_client.client import RelocClient, ServiceError
from service_support import (
    BLOCK,
    Events,
    ServiceProcess,
    endpoint,
    free_port,
    raw_session,
    service_conf,
    write_config,
)

from reloc_service.core.errors import ConfigError
from reloc_service.service.app import Service
from reloc_service.service.config import QuotasConf, ServiceConf, parse_config
from reloc_service.service.quotas import keyframe_bytes

METHOD = "sbi+p3p"
MiB = 1024 * 1024
QUOTA = wire.ErrorCode.QUOTA_EXCEEDED


def quota_conf(port: int, storage: Path | str = "", *, maps: tuple[str, ...] = ("lab",),
               **quotas: int) -> ServiceConf:
    """A thread-worker service on ``port`` with the given ``[quotas]``."""
    conf = service_conf(port, storage, maps=maps, methods=[METHOD], default_method=METHOD,
                        train_on_load=False, worker_mode="thread")
    return dataclasses.replace(conf, quotas=QuotasConf(**quotas))


def every_row(conf: ServiceConf) -> ServiceConf:
    """``conf`` storing every keypoint: the byte arithmetic of a test that wants one map
    larger than another holds only while a snapshot does not drop the keypoints without a
    landmark (a map of two keyframes has fewer of them than one of a single keyframe)."""
    return dataclasses.replace(conf, service=dataclasses.replace(conf.service,
                                                                 keyframe_descriptors="all"))


def put_keyframe(client: RelocClient, scene, kf_id: int, image: int | None = None) -> None:
    """Put keyframe ``kf_id`` (the scene's image ``image``, default ``kf_id``, as PNG: a map
    holds it, and restores it, as sent) with an inline camera, waiting for the service to
    journal it (ServiceError if refused)."""
    i = kf_id if image is None else image
    client.add_keyframe(kf_id, scene.keyframe_images[i], scene.keyframe_poses[i],
                        camera=scene.camera, image_format="png", wait=True, timeout=30)


def refusal(client: RelocClient, scene, kf_id: int, image: int | None = None) -> str:
    """The message of the QUOTA_EXCEEDED error a put of ``kf_id`` raises."""
    with pytest.raises(ServiceError) as err:
        put_keyframe(client, scene, kf_id, image)
    assert err.value.code is QUOTA, err.value
    return err.value.message


def test_quotas_section_is_read_strictly():
    conf = parse_config({"quotas": {"max_maps": 3, "max_map_bytes": 1000}})
    assert conf.quotas.max_maps == 3 and conf.quotas.max_map_bytes == 1000
    assert ServiceConf().quotas == QuotasConf()
    with pytest.raises(ConfigError, match="quotas.max_maps: expected a positive integer"):
        parse_config({"quotas": {"max_maps": 0}})
    with pytest.raises(ConfigError, match="unknown option"):
        parse_config({"quotas": {"max_keyframes": 10}})


def test_a_put_creating_a_map_beyond_max_maps_is_refused_quota_exceeded(synthetic_scene,
                                                                         tmp_path):
    """Two maps allowed, ``lab`` served: a put creates ``second``; one on ``third`` gets a
    keyframe_rejected event with QUOTA_EXCEEDED naming the quota, its limit and the use,
    add_keyframe(wait=True) raises it, and nothing of ``third`` is created."""
    port = free_port()
    storage = tmp_path / "storage"
    with Service(quota_conf(port, storage, max_maps=2)) as service:
        with RelocClient(endpoint(port), map="second", timeout=30) as second:
            put_keyframe(second, synthetic_scene, 0)
        assert "second" in service.maps
        with RelocClient(endpoint(port), map="third", timeout=30) as third:
            events = Events(third)
            message = refusal(third, synthetic_scene, 0)
            event = events.wait("keyframe_rejected", id=0, code="QUOTA_EXCEEDED")
            events.close()
        assert message == f"keyframe 0: {event.fields['message']}"
        assert "quotas.max_maps: 2 maps are served, the limit is 2" in message
        assert "'third' is not created" in message
        assert sorted(service.maps) == ["lab", "second"]
    assert not (storage / "third").exists()


def test_keyframes_beyond_a_maps_quota_are_refused_and_a_delete_frees_one(synthetic_scene):
    port = free_port()
    with Service(quota_conf(port, max_keyframes_per_map=3)) as service:
        with RelocClient(endpoint(port), map="lab", timeout=30) as client:
            events = Events(client)
            for kf_id in range(3):
                put_keyframe(client, synthetic_scene, kf_id)
            message = refusal(client, synthetic_scene, 3)
            assert ("quotas.max_keyframes_per_map: map 'lab' holds 3 keyframes, the limit "
                    "is 3") in message
            events.wait("keyframe_rejected", id=3, code="QUOTA_EXCEEDED")
            put_keyframe(client, synthetic_scene, 0, image=4)   # a replacement is not one more
            assert service.wait_idle(30)
            assert sorted(service.maps["lab"].map_state().keyframes) == [0, 1, 2]
            client.remove_keyframe(1, wait=True, timeout=30)
            put_keyframe(client, synthetic_scene, 3)
            assert service.wait_idle(30)
            assert sorted(service.maps["lab"].map_state().keyframes) == [0, 2, 3]
            events.close()


def test_bytes_per_map_and_in_total_are_counted_after_a_restart(synthetic_scene, tmp_path):
    """Keyframes on ``lab`` and ``other``; restarted with byte quotas one byte above what
    they count: a further put on ``lab`` is refused by the map's quota, on ``other`` by the
    total; deleting one of ``lab``'s keyframes makes room for ``other``'s put."""
    port = free_port()
    storage = tmp_path / "storage"
    with Service(every_row(quota_conf(port, storage, maps=("lab", "other")))) as service:
        for name, ids in (("lab", (0, 1)), ("other", (2,))):
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                for kf_id in ids:
                    put_keyframe(client, synthetic_scene, kf_id)
        assert service.wait_idle(30)
        held = {name: rt.usage.total for name, rt in service.maps.items()}
    # Restored from storage, a map holds what its snapshot keeps (no depth, images only
    # where a method reads pixels): counted as restored, and the same at every restart.
    with Service(every_row(quota_conf(port, storage, maps=("lab", "other")))) as service:
        used = {name: rt.usage.total for name, rt in service.maps.items()}
        kf1 = keyframe_bytes(service.maps["lab"].map_state().keyframes[1])
    assert all(0 < used[name] <= held[name] for name in used), (used, held)
    assert 0 < kf1 < used["lab"], used
    conf = quota_conf(port, storage, maps=("lab", "other"), max_map_bytes=used["lab"] + 1,
                      max_total_bytes=used["lab"] + used["other"] + 1)
    with Service(every_row(conf)) as service:
        assert service.maps["lab"].usage.total == used["lab"]   # counted again from storage
        with RelocClient(endpoint(port), map="lab", timeout=30) as lab, \
                RelocClient(endpoint(port), map="other", timeout=30) as other:
            message = refusal(lab, synthetic_scene, 3)
            assert (f"quotas.max_map_bytes: map 'lab' holds {used['lab']} bytes and keyframe 3 "
                    f"adds") in message
            assert f"over the limit of {used['lab'] + 1} bytes" in message
            message = refusal(other, synthetic_scene, 4)
            total = used["lab"] + used["other"]
            assert f"quotas.max_total_bytes: the maps hold {total} bytes together" in message
            lab.remove_keyframe(1, wait=True, timeout=30)
            assert service.wait_idle(30)
            assert service.maps["lab"].usage.total == used["lab"] - kf1
            put_keyframe(other, synthetic_scene, 4)
            assert service.wait_idle(30)
        assert sorted(service.maps["lab"].map_state().keyframes) == [0]
        assert sorted(service.maps["other"].map_state().keyframes) == [2, 4]


# -- the memory of refused oversized puts -----------------------------------------------------

def _status_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise AssertionError(f"no {field} in /proc/{pid}/status")


def _settled_rss_kb(pid: int, seconds: float = 3.0) -> int:
    """VmRSS once the service has had ``seconds`` to free (and trim) what it will."""
    time.sleep(seconds)
    return _status_kb(pid, "VmRSS")


@pytest.mark.slow
def test_refused_oversized_puts_give_their_memory_back(tmp_path):
    """Five 300 MiB puts (limit 32 MiB) on a ``reloc serve`` process: each is refused
    PAYLOAD_TOO_LARGE, and the service's resident memory comes back to within 64 MB of what
    it was (Zenoh's reassembly buffer is freed and the heap trimmed; it grew by about
    +550 MB and stayed there before)."""
    port = free_port()
    service = ServiceProcess(write_config(tmp_path, port), port, tmp_path / "log.txt")
    try:
        events = Events(service.client)
        pid = service.proc.pid
        before_kb = _settled_rss_kb(pid, 1.0)
        with raw_session(port) as session:
            for kf_id in range(5):
                session.put(wire.keys.keyframe("reloc", "lab", kf_id), b"\x00" * (300 * MiB),
                            congestion_control=BLOCK)
                events.wait("keyframe_rejected", id=kf_id, code="PAYLOAD_TOO_LARGE",
                            timeout=120)
        after_kb = _settled_rss_kb(pid)
        grown_mb = (after_kb - before_kb) / 1024
        print(f"five refused 300 MiB puts: VmRSS {before_kb // 1024} -> {after_kb // 1024} MB "
              f"(peak {_status_kb(pid, 'VmHWM') // 1024} MB)")
        assert grown_mb < 64, f"resident memory +{grown_mb:.0f} MB after the refusals"
        events.close()
    finally:
        service.terminate()


def test_an_oversized_put_is_followed_by_a_heap_trim(tmp_path, monkeypatch):
    """In process: a refused oversized put requests a trim that runs shortly after."""
    from reloc_service.service import memory

    if memory._malloc_trim() is None:
        pytest.skip("not glibc: no trim is requested")
    trims: list[float] = []
    monkeypatch.setattr(memory, "trim_now", lambda: trims.append(time.monotonic()) or True)
    port = free_port()
    with Service(quota_conf(port)) as service, raw_session(port) as session:
        limit = service.limits.max_payload_bytes
        for kf_id in range(3):
            session.put(wire.keys.keyframe("reloc", "lab", kf_id), b"\x00" * (limit + 1),
                        congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10
        while not trims and time.monotonic() < deadline:
            time.sleep(0.05)
    assert len(trims) >= 1, "no heap trim after the refusals"


# -- the deployment configurations --------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
DEPLOYMENT_TOMLS = sorted([ROOT / "config" / "companion.toml",
                           ROOT / "config" / "ground-station.toml",
                           *(ROOT / "deploy").rglob("*.toml")])


@pytest.mark.parametrize("path", DEPLOYMENT_TOMLS, ids=lambda p: str(p.relative_to(ROOT)))
def test_deployment_configs_create_no_map_by_put_and_set_their_quotas(path: Path):
    """No deployment lets a put create a map (only the local default does: a put cannot say
    who sent it, and none of these routers limits who may put on a new map name), and each
    sets quotas no larger than the ground station's."""
    from reloc_service.service.config import load_config

    conf = load_config(path)
    assert not conf.service.allow_new_maps, f"{path.name} creates maps from puts"
    ground = load_config(ROOT / "config" / "ground-station.toml").quotas
    assert conf.quotas != QuotasConf(), "quotas left at the code defaults"
    for field in dataclasses.fields(QuotasConf):
        assert getattr(conf.quotas, field.name) <= getattr(ground, field.name), field.name
