"""The size of each part of a saved map, per keyframe: the table of the scaling section of
``docs/performance.md`` (the bytes are measured by :func:`.scaling.part_bytes_per_keyframe`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

#: Parts in the order the table shows them (any other part found is appended).
PART_ORDER = ("features", "landmarks", "models", "thumbnails", "images", "depth", "meta")


def part_columns(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The parts any row measured, in :data:`PART_ORDER` first."""
    found = {k for r in rows for k in r.get("snapshot_bytes_per_keyframe", {}) if k != "total"}
    return [p for p in PART_ORDER if p in found] + sorted(found - set(PART_ORDER))


def part_table(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Markdown lines: kB per keyframe of each part (and the total) at each map size; no
    lines when no row measured its parts (a result of an older bench)."""
    measured = [r for r in rows if r.get("snapshot_bytes_per_keyframe")]
    if not measured:
        return []
    parts = part_columns(measured)
    lines = ["Snapshot size per keyframe and part (kB; `meta` is the manifest; depth maps "
             "are not kept once their landmarks are made and images only where a method reads "
             "them, `[service] keyframe_depth` and `keyframe_images`):", "",
             "| keyframes | " + " | ".join(parts) + " | total |",
             "|" + "|".join("---" for _ in range(len(parts) + 2)) + "|"]
    for r in measured:
        per = r["snapshot_bytes_per_keyframe"]
        cells = [_kb(per.get(p)) for p in [*parts, "total"]]
        lines.append(f"| {r['keyframes']} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _kb(value: Any) -> str:
    return "-" if value is None else f"{value / 1000:.1f}"
