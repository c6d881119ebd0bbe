"""Method strings on the service side: :class:`MethodSpec` (parsed in the wire protocol, which
both ends share) with its syntax errors raised as :class:`ConfigError`."""

from __future__ import annotations

from reloc_client.protocol.methods import MethodSpec, MethodStep

from .errors import ConfigError

__all__ = ["MethodSpec", "MethodStep", "parse_method"]


def parse_method(method: str | MethodSpec) -> MethodSpec:
    """``method`` parsed (a :class:`MethodSpec` is returned as it is); ConfigError saying
    what was expected when it is empty, has an empty step or a step of neither form."""
    if isinstance(method, MethodSpec):
        return method
    try:
        return MethodSpec.parse(method)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
