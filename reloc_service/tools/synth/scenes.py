"""The scenes ``reloc synth`` renders, by name: an explicit registry of the builders."""

from __future__ import annotations

import zlib
from collections.abc import Callable

import numpy as np

from ...core.errors import ConfigError
from .repeated import build_repeated
from .scene import Scene, build_desk, build_room

SCENES: dict[str, Callable[[np.random.Generator], Scene]] = {
    "room": build_room, "desk": build_desk, "repeated": build_repeated}


def build_scene(name: str, seed: int) -> Scene:
    """The scene ``name`` with textures drawn from ``seed`` (same seed -> same scene)."""
    if name not in SCENES:
        raise ConfigError(f"unknown scene {name!r}; expected one of {sorted(SCENES)}")
    return SCENES[name](np.random.default_rng([seed, zlib.crc32(name.encode())]))
