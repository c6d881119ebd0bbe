"""Stored keyframe statistics (:mod:`reloc_service.algorithms.pose.consistency_store`): read
back as written (values, None, not computed, the cells' entry), a file that is not theirs
refused by name, and a digest that tells apart inputs the same bytes could stand for."""

from __future__ import annotations

import re

import numpy as np
import pytest

from reloc_service.algorithms.pose.cell_correlation import CellComponents
from reloc_service.algorithms.pose.consistency_store import (
    STORE_DIR,
    InputsDigest,
    KeyframeStatistics,
    read_statistics,
    stored_kinds,
    write_statistics,
)
from reloc_service.core.errors import StorageError


def digest(seed: int) -> bytes:
    return np.random.default_rng(seed).bytes(32)


ENTRIES = {
    3: KeyframeStatistics(digest(0), {False: 1.25, True: 0.5}, True, CellComponents(2.0, 1.5, 7.25)),
    7: KeyframeStatistics(digest(1), {False: None, True: None}, True, None),
    11: KeyframeStatistics(digest(2), {False: 3.0}),   # the gated one never asked for
}


def test_stored_statistics_read_back_as_written(tmp_path) -> None:
    write_statistics(tmp_path, "sift", ENTRIES)
    assert stored_kinds(tmp_path) == ["sift"]
    assert read_statistics(tmp_path, "sift") == ENTRIES
    assert read_statistics(tmp_path, "orb") == {}
    assert write_statistics(tmp_path, "orb", {}) is None


def test_a_file_that_is_not_stored_statistics_is_refused_by_name(tmp_path) -> None:
    path = write_statistics(tmp_path, "sift", ENTRIES)
    assert path == tmp_path / STORE_DIR / "sift.npz"
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    cases = {"not a zip": None,
             "missing": {k: v for k, v in arrays.items() if k != "digests"},
             "shape": {**arrays, "digests": arrays["digests"][:, :16]},
             "code": {**arrays, "value_status": np.full_like(arrays["value_status"], 5)},
             "newer": {**arrays, "version": np.int64(99)}}
    for content in cases.values():
        if content is None:
            path.write_bytes(b"not statistics")
        else:
            np.savez(path, **content)
        with pytest.raises(StorageError, match=re.escape(str(path))):
            read_statistics(tmp_path, "sift")


def test_the_digest_tells_apart_inputs_of_the_same_bytes() -> None:
    def of(*parts: object) -> bytes:
        d = InputsDigest("test")
        for part in parts:
            d.text(part) if isinstance(part, str) else d.array(part)
        return d.digest()

    values = np.arange(6, dtype=np.float64)
    assert of(values) == of(values.copy())
    assert of(values) != of(values.reshape(2, 3))
    assert of(values) != of(values.view(np.int64))
    assert of("ab", "c") != of("a", "bc")
    assert of(values[:2], values[2:]) != of(values[:3], values[3:])
