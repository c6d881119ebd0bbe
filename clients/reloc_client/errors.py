"""The client's failures, importable without zenoh: the service refused (:class:`ServiceError`,
with an :class:`~reloc_client.protocol.ErrorCode`), was busy (:class:`ServiceBusy`), did not
answer in time (:class:`NoReplyError`) or went away while a job was awaited
(:class:`ServiceGone`)."""

from __future__ import annotations

from .protocol import ErrorCode


class ServiceError(RuntimeError):
    """The service answered with an error reply: ``code`` and the service's ``message``."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(f"{ErrorCode(code).value}: {message}")
        self.code = ErrorCode(code)
        self.message = message


class ServiceBusy(ServiceError):
    """The service is at capacity (status ``busy`` or error ``BUSY``); retry later."""


class NoReplyError(TimeoutError):
    """No service answered (none serves the map, or the reply did not come in time)."""


class ServiceGone(NoReplyError):
    """The service instances serving the map went away (their liveliness tokens) while a
    client waited for one of their jobs: the job is lost."""
