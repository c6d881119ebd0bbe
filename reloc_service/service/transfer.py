"""Maps carried over Zenoh as one file: the export and import queryables' handlers.

An export request without an id has the service write the map's export file once
(:func:`.map_transfer.export_map`, consistent while the map is served) into a directory of
its own (never the storage); chunks of it are answered by offset until it has been idle for
:data:`TRANSFER_TTL_S`. An import gathers an upload's chunks in order into a file of that
directory; the chunk marked ``finish`` has the whole file checked against its announced
SHA-256, then imported exactly as ``reloc map import`` does (every part verified before the
storage is written) and the map restored and declared. Building, verifying and importing
run on a thread of this module's own, never on the thread that dispatches queries.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode
from reloc_client.protocol.transfer import (
    ExportChunk,
    ExportRequest,
    ImportChunk,
    ImportReply,
)

from ..core.errors import StorageError
from ..storage.map_archive import file_sha256
from .map_dirs import map_dirname
from .map_transfer import export_map, import_map
from .registry import MapRegistry
from .zenoh_io import PendingQuery

log = logging.getLogger(__name__)

#: Seconds an export file or an upload is kept after its last chunk (a client that lost its
#: connection resumes within this).
TRANSFER_TTL_S = 600.0


@dataclass
class _Export:
    path: Path
    size: int
    sha256: str
    map_id: str
    last_seq: int
    used: float


@dataclass
class _Upload:
    path: Path
    total_size: int
    sha256: str
    received: int
    used: float


class Transfers:
    """The export files and uploads of one service (see module docstring)."""

    def __init__(self, storage: Path | None, registry: MapRegistry, limits: wire.Limits) -> None:
        self.storage = storage
        self.registry = registry
        self.limits = limits
        self._tmp: Path | None = None   # made on first use (most services never transfer)
        self._exports: dict[str, _Export] = {}
        self._uploads: dict[str, _Upload] = {}
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="transfer")

    @property
    def _dir(self) -> Path:
        """The directory of this service's export files and uploads (never the storage)."""
        if self._tmp is None:
            self._tmp = Path(tempfile.mkdtemp(prefix="reloc-transfer-"))
        return self._tmp

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)

    # -- dispatch (called on the query thread: hand over only) ------------------------------
    def on_export(self, map_name: str, query: PendingQuery) -> None:
        self._pool.submit(self._answer, query, lambda: self.export_chunk(map_name,
                                                                         query.payload))

    def on_import(self, map_name: str, query: PendingQuery) -> None:
        self._pool.submit(self._answer, query, lambda: self.import_chunk(map_name,
                                                                         query.payload))

    def _answer(self, query: PendingQuery, work: object) -> None:
        try:
            query.reply(work())   # type: ignore[operator]
            query.finish()
        except wire.ProtocolError as exc:
            query.reply_err(wire.encode_error(exc.code, exc.message))
        except StorageError as exc:
            query.reply_err(wire.encode_error(ErrorCode.STORAGE_ERROR, str(exc)))
        except Exception as exc:   # the service never dies on a request
            log.exception("transfer request failed")
            query.reply_err(wire.encode_error(ErrorCode.INTERNAL, f"{type(exc).__name__}: {exc}"))

    # -- export -------------------------------------------------------------------------------
    def export_chunk(self, map_name: str, payload: bytes) -> bytes:
        """The ExportChunk answering ``payload`` (an ExportRequest)."""
        request = ExportRequest.decode(payload, self.limits)
        self._expire()
        if request.export_id is None:
            export_id, export = self._new_export(map_name)
        else:
            export_id = request.export_id
            with self._lock:
                found = self._exports.get(export_id)
            if found is None:
                raise wire.ProtocolError(ErrorCode.UNKNOWN_TRANSFER, f"export {export_id}: not "
                                         f"held here (kept {TRANSFER_TTL_S:.0f} s after its "
                                         f"last chunk); start a new export")
            export = found
        export.used = time.monotonic()
        with open(export.path, "rb") as fh:
            fh.seek(min(request.offset, export.size))
            data = fh.read(request.size)
        return ExportChunk(export_id, export.size, export.sha256, min(request.offset,
                           export.size), data, export.map_id, export.last_seq).encode()

    def _new_export(self, map_name: str) -> tuple[str, _Export]:
        if self.storage is None:
            raise StorageError("this service keeps its maps in memory only (no storage): "
                               "nothing to export; serve with --storage")
        if map_name not in self.registry.maps:
            raise wire.ProtocolError(ErrorCode.UNKNOWN_MAP, f"map {map_name!r} is not served")
        export_id = uuid.uuid4().hex
        path = self._dir / f"{export_id}.relocmap"
        manifest, size = export_map(self.storage / map_dirname(map_name), path)
        export = _Export(path, size, file_sha256(path), manifest["map_id"],
                         manifest["last_seq"], time.monotonic())
        with self._lock:
            self._exports[export_id] = export
        log.info("map %s: export %s written (%d bytes)", map_name, export_id, size)
        return export_id, export

    # -- import -------------------------------------------------------------------------------
    def import_chunk(self, map_name: str, payload: bytes) -> bytes:
        """The ImportReply answering ``payload`` (an ImportChunk)."""
        chunk = ImportChunk.decode(payload, self.limits)
        wire.check_name(map_name)
        if self.storage is None:
            raise StorageError("this service keeps its maps in memory only (no storage): "
                               "it cannot import a map; serve with --storage")
        self._expire()
        upload = self._upload(chunk)
        if chunk.data and chunk.offset == upload.received:
            with open(upload.path, "ab") as fh:
                fh.write(chunk.data)
            upload.received += len(chunk.data)
        upload.used = time.monotonic()
        if not chunk.finish:
            return ImportReply(chunk.upload_id, upload.received).encode()
        return self._finish(map_name, chunk, upload)

    def _upload(self, chunk: ImportChunk) -> _Upload:
        with self._lock:
            upload = self._uploads.get(chunk.upload_id)
            if upload is None:
                upload = _Upload(self._dir / f"{chunk.upload_id}.upload", chunk.total_size,
                                 chunk.sha256, 0, time.monotonic())
                upload.path.write_bytes(b"")
                self._uploads[chunk.upload_id] = upload
        if (upload.total_size, upload.sha256) != (chunk.total_size, chunk.sha256):
            raise wire.ProtocolError(ErrorCode.BAD_VALUE, f"upload {chunk.upload_id}: "
                                     f"announced as {upload.total_size} bytes with SHA-256 "
                                     f"{upload.sha256[:16]}..., this chunk says otherwise")
        return upload

    def _finish(self, map_name: str, chunk: ImportChunk, upload: _Upload) -> bytes:
        """Check the whole file, import it, serve the map (the upload is dropped either way
        once the file is whole)."""
        if upload.received != upload.total_size:
            raise wire.ProtocolError(ErrorCode.BAD_VALUE, f"upload {chunk.upload_id}: finish "
                                     f"with {upload.received} of {upload.total_size} bytes; "
                                     f"send from offset {upload.received}")
        with self._lock:
            self._uploads.pop(chunk.upload_id, None)
        try:
            if file_sha256(upload.path) != upload.sha256:
                raise StorageError(f"upload {chunk.upload_id}: the file received does not "
                                   f"match its SHA-256; nothing imported, upload it again")
            assert self.storage is not None
            self.registry.reserve(map_name)
            try:
                done = import_map(upload.path, self.storage, name=map_name,
                                  replace=chunk.replace, owner_checked=True)
            except BaseException:
                self.registry.release(map_name)
                raise
            self.registry.serve_added(map_name)
        finally:
            upload.path.unlink(missing_ok=True)
        log.info("map %s imported (%s, %d keyframes)", map_name, done.map_id, done.keyframes)
        return ImportReply(chunk.upload_id, upload.received, True, done.map_id,
                           done.keyframes).encode()

    def _expire(self) -> None:
        """Forget exports and uploads idle for :data:`TRANSFER_TTL_S` (their files removed)."""
        cutoff = time.monotonic() - TRANSFER_TTL_S
        with self._lock:
            old = [(table, key) for table in (self._exports, self._uploads)
                   for key, item in table.items() if item.used < cutoff]
            for table, key in old:
                table.pop(key).path.unlink(missing_ok=True)  # type: ignore[attr-defined]
