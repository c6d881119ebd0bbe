"""A map carried as one file over Zenoh (``reloc_client.protocol.transfer``), resumable.

:func:`download_export` writes ``FILE.partial`` and, next to it, ``FILE.partial.json`` (the
export id, size and SHA-256 the service announced): run again after a lost connection, it
asks for the bytes after those it holds (a new export if the service no longer holds that
one), checks the whole file's SHA-256 and renames it to ``FILE``. :func:`upload_import`
sends under an upload id made of the file's SHA-256 and the map name, so running it again
asks the service where that upload stands and sends only the rest.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .protocol import ErrorCode
from .protocol.transfer import (
    MAX_CHUNK,
    ExportChunk,
    ExportRequest,
    ImportChunk,
    ImportReply,
    export_key,
    import_key,
)

if TYPE_CHECKING:
    from .client import RelocClient

#: Progress callback: (bytes done, total bytes).
Progress = Callable[[int, int], None]
#: Seconds the service may take to write the export file or to verify and restore an import.
BUILD_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class Transferred:
    """A finished transfer: the file, its size and SHA-256, the map's identity, and the
    offset it started from (above 0: resumed)."""

    path: Path
    size: int
    sha256: str
    map_id: str
    resumed_from: int


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


# -- export -----------------------------------------------------------------------------------

def download_export(client: RelocClient, file: Path, *, chunk_size: int = MAX_CHUNK,
                    progress: Progress | None = None) -> Transferred:
    """Export ``client.map`` from its service into ``file`` (see module docstring)."""
    from .errors import ServiceError

    partial = file.with_name(file.name + ".partial")
    state_path = file.with_name(file.name + ".partial.json")
    export_id, offset = _resume_point(partial, state_path)
    resumed_from = offset
    key = export_key(client.prefix, client.map)
    while True:
        try:
            chunk = _export_chunk(client, key, ExportRequest(offset, chunk_size, export_id))
        except ServiceError as exc:
            if exc.code is not ErrorCode.UNKNOWN_TRANSFER or export_id is None:
                raise
            export_id, offset, resumed_from = None, 0, 0   # expired: a new export
            partial.write_bytes(b"")
            continue
        if export_id is None:
            export_id = chunk.export_id
            state_path.write_text(json.dumps({"export_id": export_id,
                                              "total_size": chunk.total_size,
                                              "sha256": chunk.sha256}))
        with open(partial, "ab") as fh:
            fh.write(chunk.data)
        offset += len(chunk.data)
        if progress is not None:
            progress(offset, chunk.total_size)
        if offset >= chunk.total_size or not chunk.data:
            break
    return _finish_download(partial, state_path, file, chunk, resumed_from)


def _resume_point(partial: Path, state_path: Path) -> tuple[str | None, int]:
    """(export id, bytes held) of an interrupted download, else (None, 0) with an empty
    partial file."""
    try:
        state = json.loads(state_path.read_text())
        return str(state["export_id"]), partial.stat().st_size
    except (OSError, ValueError, KeyError, TypeError):
        partial.write_bytes(b"")
        state_path.unlink(missing_ok=True)
        return None, 0


def _export_chunk(client: RelocClient, key: str, request: ExportRequest) -> ExportChunk:
    timeout = BUILD_TIMEOUT_S if request.export_id is None else client.timeout
    return ExportChunk.decode(client._query_one(key, request.encode(), timeout),
                              client.limits)


def _finish_download(partial: Path, state_path: Path, file: Path, last: ExportChunk,
                     resumed_from: int) -> Transferred:
    from .errors import ServiceError

    digest = file_sha256(partial)
    if partial.stat().st_size != last.total_size or digest != last.sha256:
        partial.unlink(missing_ok=True)
        state_path.unlink(missing_ok=True)
        raise ServiceError(ErrorCode.STORAGE_ERROR, f"{file}: the bytes received do not match "
                           f"the export's size and SHA-256; removed, run the export again")
    os.replace(partial, file)
    state_path.unlink(missing_ok=True)
    return Transferred(file, last.total_size, digest, last.map_id, resumed_from)


# -- import -----------------------------------------------------------------------------------

def upload_import(client: RelocClient, file: Path, *, name: str | None = None,
                  replace: bool = False, chunk_size: int = MAX_CHUNK,
                  progress: Progress | None = None) -> tuple[Transferred, ImportReply]:
    """Import ``file`` into the service as map ``name`` (default ``client.map``); the
    service verifies it in full before serving it (see module docstring)."""
    map_name = name or client.map
    total, sha256 = file.stat().st_size, file_sha256(file)
    upload_id = hashlib.sha256(f"{sha256}:{map_name}".encode()).hexdigest()[:32]
    key = import_key(client.prefix, map_name)

    def send(chunk: ImportChunk, timeout: float) -> ImportReply:
        return ImportReply.decode(client._query_one(key, chunk.encode(), timeout),
                                  client.limits)

    offset = send(ImportChunk(upload_id, total, sha256), client.timeout).received
    resumed_from = offset
    with open(file, "rb") as fh:
        while offset < total:
            fh.seek(offset)
            data = fh.read(chunk_size)
            offset = send(ImportChunk(upload_id, total, sha256, offset, data),
                          client.timeout).received
            if progress is not None:
                progress(offset, total)
    reply = send(ImportChunk(upload_id, total, sha256, total, finish=True, replace=replace),
                 BUILD_TIMEOUT_S)
    return Transferred(file, total, sha256, reply.map_id or "", resumed_from), reply
