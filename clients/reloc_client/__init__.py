"""Client of the reloc relocalization service: the wire protocol and a Zenoh client.

``reloc_client.protocol`` needs only msgpack and numpy; the client classes (which need
zenoh) are imported on first use, so ``import reloc_client.protocol`` never loads zenoh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .protocol import PROTOCOL_VERSION, ErrorCode, ProtocolError

if TYPE_CHECKING:
    from .client import (
        NoReplyError,
        RelocClient,
        RelocResult,
        RelocStatus,
        ServiceBusy,
        ServiceError,
        ServiceGone,
    )
    from .outbox import Outbox

__version__ = "0.1.0"

_CLIENT_NAMES = {"RelocClient", "RelocResult", "RelocStatus", "ServiceError", "ServiceBusy",
                 "NoReplyError", "ServiceGone", "Outbox"}

__all__ = ["PROTOCOL_VERSION", "ErrorCode", "ProtocolError", "NoReplyError", "RelocClient",
           "RelocResult", "RelocStatus", "ServiceBusy", "ServiceError", "ServiceGone", "Outbox"]


def __getattr__(name: str) -> Any:
    if name == "Outbox":
        from .outbox import Outbox

        return Outbox
    if name in _CLIENT_NAMES:
        from . import client

        return getattr(client, name)
    raise AttributeError(f"module 'reloc_client' has no attribute {name!r}")
