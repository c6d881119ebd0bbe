"""The bench's map size per part: bytes per keyframe of each part of a saved snapshot."""

from __future__ import annotations

from reloc_service.storage.keyframe_parts import EVERYTHING, StoredParts
from reloc_service.storage.snapshot import save_map
from reloc_service.storage.snapshot_files import current_snapshot
from reloc_service.tools.bench.map_size import part_table
from reloc_service.tools.bench.scaling import part_bytes_per_keyframe


def test_the_parts_add_up_to_the_snapshot_and_a_compact_one_has_no_images(
        tmp_path, synthetic_map):
    n = len(synthetic_map.keyframes)
    save_map(synthetic_map, tmp_path / "full", parts=EVERYTHING)
    save_map(synthetic_map, tmp_path / "compact", parts=StoredParts())
    full = part_bytes_per_keyframe(tmp_path / "full", n)
    compact = part_bytes_per_keyframe(tmp_path / "compact", n)
    on_disk = sum(p.stat().st_size for p in current_snapshot(tmp_path / "full").rglob("*")
                  if p.is_file())
    assert abs(full["total"] * n - on_disk) < 1e-6 * on_disk
    assert {"images", "features", "landmarks", "meta"} <= full.keys()
    assert "images" not in compact and "depth" not in compact
    assert compact["features"] == full["features"]
    assert compact["total"] < full["total"] - full["images"] + 1000   # the manifest grows a bit


def test_the_table_shows_each_part_in_kb_and_nothing_for_an_older_result():
    rows = [{"keyframes": 10, "snapshot_bytes_per_keyframe": {
        "features": 20000.0, "landmarks": 5000.0, "meta": 500.0, "total": 25500.0}}]
    lines = part_table(rows)
    assert "| keyframes | features | landmarks | meta | total |" in lines
    assert "| 10 | 20.0 | 5.0 | 0.5 | 25.5 |" in lines
    assert part_table([{"keyframes": 10}]) == []
