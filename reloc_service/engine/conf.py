"""What an :class:`~.engine.Engine` is made with: the methods it keeps ready, the plugins'
options, the map building configuration and what a save stores of each keyframe."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from ..algorithms.relocalizers.factory import DEFAULT_METHOD
from ..core.errors import ConfigError
from ..core.mapping import MappingConf
from ..storage.keyframe_parts import StoredParts


@dataclass(frozen=True)
class EngineConf:
    """Methods kept ready (the first is the default), plugin options (plugin name -> option
    dict, as :func:`create_relocalizer` takes them), the map building configuration and what
    a save stores of each keyframe's depth and image (:class:`StoredParts`)."""

    methods: tuple[str, ...] = (DEFAULT_METHOD,)
    options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    mapping: MappingConf = field(default_factory=MappingConf)
    stored: StoredParts = field(default_factory=StoredParts)

    def __post_init__(self) -> None:
        methods = tuple(self.methods) if isinstance(self.methods, list | tuple) else None
        if not methods or not all(isinstance(m, str) and m.strip() for m in methods):
            raise ConfigError(f"engine.methods: expected a non-empty list of method strings "
                              f"(e.g. ['sbi+p3p']), got {self.methods!r}")
        object.__setattr__(self, "methods", tuple(m.strip() for m in methods))
        if not isinstance(self.options, Mapping) or not all(
                isinstance(v, Mapping) for v in self.options.values()):
            raise ConfigError(f"engine.options: expected plugin name -> option table, got "
                              f"{self.options!r}")
        object.__setattr__(self, "options", MappingProxyType(
            {k: MappingProxyType(dict(v)) for k, v in self.options.items()}))
        if isinstance(self.mapping, Mapping):
            object.__setattr__(self, "mapping", MappingConf.from_options(self.mapping))

    @property
    def default_method(self) -> str:
        return self.methods[0]
