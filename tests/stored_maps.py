"""The stored-map fixtures of the storage tests (not a test module): one small map directory
per snapshot format, each written by that format's code, that a later reloc must still load."""

from __future__ import annotations

from pathlib import Path

DATA = Path(__file__).parent / "data"
#: written by the format-4 code
V4_MAP = DATA / "map_v4"
#: written by the format-5 code: map_v4 loaded and saved
V5_MAP = DATA / "map_v5"
#: written by the format-6 code: map_v5 loaded and saved with lossless depth and every image
V6_MAP = DATA / "map_v6"
#: written by the format-7 code: map_v6 loaded and saved with lossless depth and every image
V7_MAP = DATA / "map_v7"
#: written by the format-8 code: map_v7 loaded and saved with lossless depth, every image and
#: one descriptor per landmark (no row keeping its own)
V8_MAP = DATA / "map_v8"


def stored_map(version: int) -> Path:
    """The map directory of a snapshot written in format ``version`` (tests/data/map_vN)."""
    return DATA / f"map_v{version}"
