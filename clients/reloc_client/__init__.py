"""Client of the reloc relocalization service: the wire protocol, the result type and a
Zenoh client.

``reloc_client.protocol`` and ``reloc_client.result`` need only msgpack and numpy; the client
classes (which need zenoh) are imported on first use, so importing the protocol or the result
(as the service does) never loads zenoh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .protocol import PROTOCOL_VERSION, ErrorCode, ProtocolError

if TYPE_CHECKING:
    from .client import RelocClient
    from .errors import NoReplyError, ServiceBusy, ServiceError, ServiceGone
    from .outbox import Outbox
    from .result import RelocResult, RelocStatus, reply_from_result, result_from_reply

__version__ = "0.1.0"

_ERROR_NAMES = {"ServiceError", "ServiceBusy", "NoReplyError", "ServiceGone"}
_RESULT_NAMES = {"RelocResult", "RelocStatus", "reply_from_result", "result_from_reply"}

__all__ = ["PROTOCOL_VERSION", "ErrorCode", "ProtocolError", "NoReplyError", "RelocClient",
           "RelocResult", "RelocStatus", "ServiceBusy", "ServiceError", "ServiceGone", "Outbox",
           "reply_from_result", "result_from_reply"]


def __getattr__(name: str) -> Any:
    if name == "Outbox":
        from .outbox import Outbox

        return Outbox
    if name in _RESULT_NAMES:
        from . import result

        return getattr(result, name)
    if name in _ERROR_NAMES:
        from . import errors

        return getattr(errors, name)
    if name == "RelocClient":
        from .client import RelocClient

        return RelocClient
    raise AttributeError(f"module 'reloc_client' has no attribute {name!r}")
