"""Maps carried as one file over Zenoh: the export and import keys and their messages.

Export: queries on ``<prefix>/<map>/export`` with an :class:`ExportRequest` each answered by
one :class:`ExportChunk`. The first request (no ``export_id``) has the service write the
map's export file once (``reloc map export``); every reply names it (``export_id``) and
gives the file's size and SHA-256, so a client asks for the next chunk by offset, resumes
after a lost connection from the bytes it holds, and checks the whole file at the end.

Import: queries on ``<prefix>/<map>/import`` with an :class:`ImportChunk` each, under an
``upload_id`` the client chooses (the SHA-256 of the file and the map name: running the same
import again resumes it). Each is answered by an :class:`ImportReply` saying how many bytes
the service holds (a chunk at another offset is not taken: the reply tells the client where
to continue). The chunk with ``finish`` set makes the service verify the file as
``reloc map import`` does and serve the map; the reply says so (``done``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from .checks import ErrorCode, Limits, ProtocolError, _bool, _bytes, _fail, _Fields, _int
from .keys import check_name, check_prefix
from .message_base import Message

#: Largest chunk of an export or import (well under the default payload limit of 32 MB).
MAX_CHUNK = 4 * 1024 * 1024
#: Largest export file announced or imported (a map of 10000 full-size keyframes).
MAX_FILE_BYTES = 2**40


def export_key(prefix: str, map_name: str) -> str:
    """``<prefix>/<map>/export``: queryable, ExportRequest -> ExportChunk."""
    return f"{check_prefix(prefix)}/{check_name(map_name)}/export"


def import_key(prefix: str, map_name: str) -> str:
    """``<prefix>/<map>/import``: queryable, ImportChunk -> ImportReply (the map need not be
    served yet: the service answers for any map name)."""
    return f"{check_prefix(prefix)}/{check_name(map_name)}/import"


def _hex(value: Any, path: str, lo: int = 32, hi: int = 64) -> str:
    """``lo`` to ``hi`` lowercase hex digits (an id, a SHA-256)."""
    if not isinstance(value, str):
        raise _fail(ErrorCode.WRONG_TYPE, path, "a string of hex digits", value)
    if not lo <= len(value) <= hi or any(c not in "0123456789abcdef" for c in value):
        raise _fail(ErrorCode.BAD_VALUE, path, f"{lo} to {hi} lowercase hex digits", value)
    return value


def _sha256(value: Any, path: str) -> str:
    return _hex(value, path, 64, 64)


def _offset(value: Any, path: str) -> int:
    return _int(value, path, lo=0, hi=MAX_FILE_BYTES)


def _chunk(value: Any, path: str) -> bytes:
    data = _bytes(value, path, nonempty=False)
    if len(data) > MAX_CHUNK:
        raise ProtocolError(ErrorCode.PAYLOAD_TOO_LARGE,
                            f"{path}: {len(data)} bytes; expected at most {MAX_CHUNK}")
    return data


@dataclass(frozen=True)
class ExportRequest(Message):
    """Query on ``<prefix>/<map>/export``: ``size`` bytes from ``offset`` of export
    ``export_id`` (None: write a new export file of the map and answer from it)."""

    NAME: ClassVar[str] = "export_request"
    offset: int = 0
    size: int = MAX_CHUNK
    export_id: str | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"offset": self.offset, "size": self.size, "export_id": self.export_id}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> ExportRequest:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.opt("offset", _offset, 0),
                  f.opt("size", lambda v, p: _int(v, p, lo=1, hi=MAX_CHUNK), MAX_CHUNK),
                  f.opt("export_id", _hex))
        f.done()
        return out


@dataclass(frozen=True)
class ExportChunk(Message):
    """Reply to an ExportRequest: the bytes of export ``export_id`` from ``offset`` (empty at
    the end), with the file's ``total_size`` and ``sha256`` and the map's identity."""

    NAME: ClassVar[str] = "export_chunk"
    export_id: str
    total_size: int
    sha256: str
    offset: int
    data: bytes
    map_id: str
    last_seq: int

    def to_wire(self) -> dict[str, Any]:
        return {"export_id": self.export_id, "total_size": self.total_size,
                "sha256": self.sha256, "offset": self.offset, "data": self.data,
                "map_id": self.map_id, "last_seq": self.last_seq}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> ExportChunk:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.req("export_id", _hex), f.req("total_size", _offset),
                  f.req("sha256", _sha256), f.req("offset", _offset),
                  f.req("data", _chunk), f.req("map_id", _hex),
                  f.req("last_seq", lambda v, p: _int(v, p, lo=0)))
        f.done()
        if out.offset + len(out.data) > out.total_size:
            raise ProtocolError(ErrorCode.BAD_VALUE,
                                f"{path}: bytes {out.offset}..{out.offset + len(out.data)} "
                                f"past the file's {out.total_size}")
        return out


@dataclass(frozen=True)
class ImportChunk(Message):
    """Query on ``<prefix>/<map>/import``: ``data`` at ``offset`` of the export file
    ``upload_id`` (``total_size`` bytes, SHA-256 ``sha256``); with ``finish`` (the file
    whole) the service verifies and serves it, replacing a map of that name only with
    ``replace``. An empty ``data`` asks where the upload stands."""

    NAME: ClassVar[str] = "import_chunk"
    upload_id: str
    total_size: int
    sha256: str
    offset: int = 0
    data: bytes = b""
    finish: bool = False
    replace: bool = False

    def to_wire(self) -> dict[str, Any]:
        return {"upload_id": self.upload_id, "total_size": self.total_size,
                "sha256": self.sha256, "offset": self.offset, "data": self.data,
                "finish": self.finish, "replace": self.replace}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> ImportChunk:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.req("upload_id", _hex), f.req("total_size", _offset),
                  f.req("sha256", _sha256), f.opt("offset", _offset, 0),
                  f.opt("data", _chunk, b""), f.opt("finish", _bool, False),
                  f.opt("replace", _bool, False))
        f.done()
        if out.offset + len(out.data) > out.total_size:
            raise ProtocolError(ErrorCode.BAD_VALUE,
                                f"{path}: bytes {out.offset}..{out.offset + len(out.data)} "
                                f"past the announced total_size {out.total_size}")
        return out


@dataclass(frozen=True)
class ImportReply(Message):
    """Reply to an ImportChunk: the bytes of upload ``upload_id`` the service holds
    (``received``: send from there), and once ``done`` the map served with its identity
    and keyframe count."""

    NAME: ClassVar[str] = "import_reply"
    upload_id: str
    received: int
    done: bool = False
    map_id: str | None = None
    keyframes: int | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"upload_id": self.upload_id, "received": self.received, "done": self.done,
                "map_id": self.map_id, "keyframes": self.keyframes}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> ImportReply:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.req("upload_id", _hex), f.req("received", _offset),
                  f.opt("done", _bool, False), f.opt("map_id", _hex),
                  f.opt("keyframes", lambda v, p: _int(v, p, lo=0)))
        f.done()
        return out


TRANSFER_MESSAGES: tuple[type[Message], ...] = (ExportRequest, ExportChunk, ImportChunk,
                                                ImportReply)
