"""What the service's map and a worker process's replica share: the write operations as the
journal stores them and the pipe carries them, and the one way a change applies, so that the
same changes give the same map in the service, in a replica and after a restart."""

import pickle
from typing import Any

import msgpack
from reloc_client import protocol as wire

from reloc_service.core.mapping import MappingConf
from reloc_service.engine import Engine, EngineConf
from reloc_service.service.processes import EngineSpec, ReplicaMap
from reloc_service.service.runtime import MapRuntime
from reloc_service.service.served import WriteOp
from reloc_service.storage.journal import Journal

METHODS = ("sbi+p3p",)
MAPPING = {"max_features": 400}
LIMITS = wire.Limits()


def _engine() -> Engine:
    return Engine(EngineConf(methods=METHODS, mapping=MappingConf.from_options(MAPPING)))


def _runtime(directory, events: list[tuple[str, Any]]) -> MapRuntime:
    rt = MapRuntime("m", _engine(), instance="test", limits=LIMITS, methods=METHODS,
                    default_method=METHODS[0], directory=directory,
                    publish=lambda _map, kind, fields: events.append((kind.value, fields)))
    rt.restore()   # opens the journal for appending, as the service does
    return rt


class _Pipe:
    """Forwards a runtime's changes to a replica as the worker pipe does: pickled messages
    ``(op string, map, *args)``, the op parsed back on the worker's side."""

    def __init__(self, replica: ReplicaMap) -> None:
        self.replica = replica
        self.messages: list[tuple[Any, ...]] = []

    def forward(self, name: str, op: WriteOp, *args: Any) -> None:
        msg = pickle.loads(pickle.dumps((op.value, name, *args)))
        self.messages.append(msg)
        kind, _name, *rest = msg
        self.replica.apply_change(WriteOp(kind), *rest)

    def rebase(self, rt: MapRuntime) -> None:
        raise AssertionError("no training here")


def _camera_put(scene) -> bytes:
    return wire.CameraPut("cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode()


def _keyframe_put(scene, kf_id: int) -> bytes:
    return wire.KeyframePut(
        id=kf_id, image=wire.WireImage.from_array(scene.keyframe_images[kf_id]),
        world_from_cam=wire.WirePose.from_matrix(scene.keyframe_poses[kf_id]),
        camera_id="cam0").encode()


def test_write_ops_are_the_journal_strings():
    assert {op.name: op.value for op in WriteOp} == {"KEYFRAME": "kf", "DELETE": "del",
                                                     "CAMERA": "cam"}
    assert WriteOp("del") is WriteOp.DELETE
    assert msgpack.unpackb(msgpack.packb({"op": WriteOp.CAMERA.value})) == {"op": "cam"}


def test_a_replica_and_a_restart_hold_the_map_the_runtime_built(tmp_path, synthetic_scene):
    events: list[tuple[str, Any]] = []
    rt = _runtime(tmp_path, events)
    spec = EngineSpec.of(METHODS, {}, MAPPING, LIMITS)
    replica = ReplicaMap("m", _engine(), spec, rt.cameras())
    pipe = _Pipe(replica)
    rt.replicas = pipe
    rt.put_camera("cam0", _camera_put(synthetic_scene))
    for kf_id in (0, 1, 2):
        rt.put_keyframe(kf_id, _keyframe_put(synthetic_scene, kf_id))
    rt.delete_keyframe(1)
    rt.delete_keyframe(7)   # not in the map: rejected, neither journaled nor forwarded
    rt.close(final_snapshot=False)

    assert [m[0] for m in pipe.messages] == ["cam", "kf", "kf", "kf", "del"]
    records = [msgpack.unpackb(raw) for raw in Journal(tmp_path / "journal").replay(0)]
    assert [(r["op"], r["id"]) for r in records] == [("cam", "cam0"), ("kf", 0), ("kf", 1),
                                                     ("kf", 2), ("del", 1)]
    assert ("keyframe_rejected", {"id": 7, "code": "UNKNOWN_KEYFRAME"}) in [
        (kind, {k: f[k] for k in ("id", "code") if k in f}) for kind, f in events]

    restarted = _runtime(tmp_path, [])
    for other in (replica, restarted):
        assert sorted(other.map_state().keyframes) == [0, 2]
        assert other.map_state().version == rt.map_state().version
        assert other.camera_ids() == ["cam0"]
        assert other.camera("cam0").to_dict() == synthetic_scene.camera.to_dict()
    restarted.close(final_snapshot=False)
