"""Explicit plugin registries with typed configurations (hloc-style ``default_conf``, made strict).

Every plugin class declares a frozen dataclass ``Conf``; :func:`make_conf` builds it from a dict
and rejects unknown keys and wrong types with a :class:`ConfigError` that lists what is allowed.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Generic, Protocol, TypeVar

from .errors import ConfigError


class Plugin(Protocol):
    """What a registered class carries: the name it was registered under (set by
    :meth:`Registry.register`)."""

    name: ClassVar[str]


P = TypeVar("P", bound=Plugin)
T = TypeVar("T")


class Registry(dict[str, type[P]], Generic[P]):
    """A name -> class table filled by the :meth:`register` decorator; ``Registry[PlaceFinder]``
    holds subclasses of ``PlaceFinder``."""

    def __init__(self, what: str) -> None:
        super().__init__()
        self.what = what

    def register(self, name: str) -> Callable[[type[P]], type[P]]:
        def deco(cls: type[P]) -> type[P]:
            if name in self:
                raise ValueError(f"duplicate {self.what} {name!r}")
            cls.name = name
            self[name] = cls
            return cls
        return deco

    def lookup(self, name: str) -> type[P]:
        if name not in self:
            raise ConfigError(f"unknown {self.what} {name!r}; expected one of {sorted(self)}")
        return self[name]


def make_conf(conf_cls: type[T], options: Mapping[str, Any] | None, *, owner: str) -> T:
    """Build the frozen ``conf_cls`` from ``options``; ConfigError on unknown keys or types."""
    options = dict(options or {})
    fields = {f.name: f for f in dataclasses.fields(conf_cls)}  # type: ignore[arg-type]
    unknown = sorted(set(options) - set(fields))
    if unknown:
        raise ConfigError(f"{owner}: unknown option(s) {unknown}; expected some of {sorted(fields)}")
    hints = typing.get_type_hints(conf_cls)
    for key, value in options.items():
        options[key] = _coerce(value, hints[key], f"{owner}.{key}")
    try:
        return conf_cls(**options)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{owner}: {exc}") from exc


def _coerce(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(hint):
            if arg is type(None) and value is None:
                return None
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        error: ConfigError | None = None
        for arg in args:   # the first member the value fits (``int | Mapping[str, int]``)
            try:
                return _coerce(value, arg, where)
            except ConfigError as exc:
                error = error or exc
        assert error is not None
        raise error
    if hint is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if hint is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if hint is bool and isinstance(value, bool):
        return value
    if hint is str and isinstance(value, str):
        return value
    if origin is tuple and isinstance(value, list | tuple):
        return tuple(value)
    if hint in (float, int, bool, str):
        raise ConfigError(f"{where}: expected {hint.__name__}, got {value!r}")
    return value
