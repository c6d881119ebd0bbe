"""``reloc-client export|import`` over Zenoh: a map exported by one service and imported by
another answers the same queries with the same poses; an interrupted transfer resumes from
the bytes already held; a damaged upload is refused by name and nothing is served or stored.
Real services on loopback (separate ports, not connected to each other), real files."""
# ruff: noqa: E402

from __future__ import annotations

import json
import tarfile

import numpy as np
import pytest
from reloc_client import protocol as wire
from reloc_client.cli import main as reloc_client
from reloc_client.client import NoReplyError, RelocClient, ServiceError
from reloc_client.protocol.transfer import (
    MAX_CHUNK,
    ExportChunk,
    ExportRequest,
    ImportChunk,
    ImportReply,
    export_key,
)
from reloc_client.transfer import download_export, upload_import
from service_support import MAP, endpoint, free_port, service_conf
from storage_support import fill_map, listing, query_poses

from reloc_service.service.app import Service

KEYFRAMES = 5
CHUNK = 64 * 1024


class Interrupted(Exception):
    """What a lost connection looks like to the caller of a transfer."""


def _stop_after(chunks: int):
    seen = []

    def progress(done: int, total: int) -> None:
        seen.append(done)
        if len(seen) >= chunks and done < total:
            raise Interrupted(f"connection lost after {done} of {total} bytes")
    return progress


@pytest.fixture(scope="module")
def two_services(synthetic_scene, tmp_path_factory):
    """Service A serving map ``lab`` restored from its snapshot (stopped once with a final
    snapshot, so both ends restore the same files alone) and service B with an empty storage."""
    root = tmp_path_factory.mktemp("zenoh-transfer")
    with Service(service_conf(free_port(), root / "a", maps=(MAP,))) as builder:
        fill_map(builder, synthetic_scene, range(KEYFRAMES))
    port_a, port_b = free_port(), free_port()
    # queries on threads: no worker processes to start for a few queries (that they answer
    # alike is test_processes')
    with Service(service_conf(port_a, root / "a", maps=(MAP,), worker_mode="thread")), \
            Service(service_conf(port_b, root / "b", worker_mode="thread")):
        yield root, port_a, port_b


def test_export_then_import_over_zenoh_gives_identical_answers(two_services, synthetic_scene,
                                                               tmp_path, capsys):
    root, port_a, port_b = two_services
    file = tmp_path / "lab.relocmap"
    assert reloc_client(["--connect", endpoint(port_a), "--timeout", "30", "export", MAP,
                         str(file)]) == 0
    exported = json.loads(capsys.readouterr().out)
    assert exported["bytes"] == file.stat().st_size and exported["resumed_from"] == 0
    assert reloc_client(["--connect", endpoint(port_b), "--timeout", "30", "import", str(file),
                         "--name", "lab-copy"]) == 0
    imported = json.loads(capsys.readouterr().out)
    assert imported["keyframes"] == KEYFRAMES
    assert imported["map_id"] == exported["map_id"]   # the identity travels
    expected = query_poses(port_a, synthetic_scene)
    for a, b in zip(expected, query_poses(port_b, synthetic_scene, "lab-copy"), strict=True):
        np.testing.assert_array_equal(a, b)


def test_an_interrupted_export_and_import_resume(two_services, tmp_path):
    root, port_a, port_b = two_services
    file = tmp_path / "lab.relocmap"
    with RelocClient(endpoint(port_a), map=MAP, timeout=30) as client:
        with pytest.raises(Interrupted):
            download_export(client, file, chunk_size=CHUNK, progress=_stop_after(3))
        held = (tmp_path / "lab.relocmap.partial").stat().st_size
        assert held == 3 * CHUNK and not file.exists()
        done = download_export(client, file, chunk_size=CHUNK)
    assert done.resumed_from == held and done.size == file.stat().st_size
    with RelocClient(endpoint(port_b), map="lab-resumed", timeout=30) as client:
        with pytest.raises(Interrupted):
            upload_import(client, file, chunk_size=CHUNK, progress=_stop_after(2))
        with pytest.raises(NoReplyError):
            client.status(timeout=1)   # nothing served before the whole file is verified
        moved, reply = upload_import(client, file, chunk_size=CHUNK)
        assert moved.resumed_from == 2 * CHUNK
        assert reply.done and reply.keyframes == KEYFRAMES
        assert client.status().keyframes == KEYFRAMES


def test_a_damaged_upload_is_refused_by_name_and_nothing_is_stored(two_services, tmp_path):
    root, port_a, port_b = two_services
    good = tmp_path / "lab.relocmap"
    with RelocClient(endpoint(port_a), map=MAP, timeout=30) as client:
        download_export(client, good)
    with tarfile.open(good) as tar:
        member = next(m for m in tar if "/features/" in m.name)
    raw = bytearray(good.read_bytes())
    raw[member.offset_data + 10] ^= 0x01
    bad = tmp_path / "bad.relocmap"
    bad.write_bytes(bytes(raw))
    with RelocClient(endpoint(port_b), map="lab-bad", timeout=30) as client:
        with pytest.raises(ServiceError) as refused:
            upload_import(client, bad)
        assert refused.value.code is wire.ErrorCode.STORAGE_ERROR
        assert f"part {member.name}: checksum mismatch" in refused.value.message
        with pytest.raises(NoReplyError):
            client.status(timeout=1)
    # nothing written into the storage: no map directory, no hidden staging directory
    assert [p for p, _ in listing(root / "b") if "lab-bad" in p or ".import-" in p] == []


def test_an_unknown_export_id_is_named(two_services):
    _, port_a, _ = two_services
    with RelocClient(endpoint(port_a), map=MAP, timeout=10) as client:
        key = export_key(client.prefix, MAP)
        request = ExportRequest(0, 1024, "0" * 32)
        with pytest.raises(ServiceError) as refused:
            client._query_one(key, request.encode(), 10)
    assert refused.value.code is wire.ErrorCode.UNKNOWN_TRANSFER
    assert "start a new export" in refused.value.message


@pytest.mark.parametrize("message, code", [
    (lambda: ExportChunk("a" * 32, 10, "b" * 64, 8, b"abc", "c" * 32, 1), "BAD_VALUE"),
    (lambda: ImportChunk("A" * 32, 10, "b" * 64), "BAD_VALUE"),
    (lambda: ImportChunk("a" * 32, MAX_CHUNK + 1, "b" * 64, 0, b"x" * (MAX_CHUNK + 1)),
     "PAYLOAD_TOO_LARGE"),
    (lambda: ExportRequest(0, MAX_CHUNK + 1), "BAD_VALUE"),
])
def test_transfer_messages_are_validated(message, code):
    with pytest.raises(wire.ProtocolError) as refused:
        message().encode()
    assert refused.value.code.value == code


def test_transfer_messages_round_trip():
    for message in (ExportRequest(5, 100, "a" * 32),
                    ExportChunk("a" * 32, 10, "b" * 64, 7, b"abc", "c" * 32, 4),
                    ImportChunk("a" * 32, 10, "b" * 64, 2, b"xyz", finish=True, replace=True),
                    ImportReply("a" * 32, 10, True, "c" * 32, 3)):
        assert type(message).decode(message.encode()) == message
