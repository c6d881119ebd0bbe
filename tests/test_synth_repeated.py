"""The ``repeated`` synth scene: pictures hung several times, periodic tiles, identical
furniture; and its presets."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.synth import PRESETS, render_dataset
from reloc_service.tools.synth.repeated import (
    LAYOUT,
    MODELS,
    VARIANTS,
    hang,
    periodic_tiles,
    variant,
)
from reloc_service.tools.synth.scenes import build_scene


def test_periodic_tiles_repeat_every_two_tiles_exactly() -> None:
    tex = periodic_tiles(np.random.default_rng(0), (300, 500), "brick", 60, grout_px=2,
                         contrast=0.6, brightness=0.6)
    assert tex.shape == (300, 500)
    np.testing.assert_array_equal(tex[:, :380], tex[:, 120:500])
    np.testing.assert_array_equal(tex[:180, :], tex[120:300, :])
    assert tex[:, :120].std() > 0.05  # a picture, not a flat colour


def test_variants_are_the_picture_mirrored_cropped_and_tiled() -> None:
    rng = np.random.default_rng(0)
    picture = rng.random((40, 60)).astype(np.float32)
    np.testing.assert_array_equal(variant(rng, picture, "same"), picture)
    np.testing.assert_array_equal(variant(rng, picture, "mirror"), picture[:, ::-1])
    mosaic = variant(rng, picture, "mosaic")
    assert mosaic.shape == (80, 120)
    np.testing.assert_array_equal(mosaic[:40, :60], picture)
    np.testing.assert_array_equal(mosaic[:40, 60:], picture[:, ::-1])
    crop = variant(rng, picture, "crop")
    assert 24 <= crop.shape[0] < 40 and 36 <= crop.shape[1] < 60
    windows = np.lib.stride_tricks.sliding_window_view(picture, crop.shape)
    assert np.any(np.all(windows == crop, axis=(2, 3)))  # a window of the picture
    with pytest.raises(ValueError, match="expected one of"):
        variant(rng, picture, "rotate")
    assert set(VARIANTS) == {"same", "mirror", "crop", "mosaic"}


def test_hang_clips_at_the_texture_edge() -> None:
    tex = np.zeros((100, 100), np.float32)
    hang(tex, 0.01, np.ones((20, 20), np.float32), (0.95, 0.5), 0.3, frame=0.5)
    assert tex[:, 80:].max() == 1.0 and tex[:, :70].max() == 0.0


def test_identical_furniture_shares_its_textures() -> None:
    scene = build_scene("repeated", 0)
    ids, counts = np.unique(scene.texture_ids, return_counts=True)
    copies = {m: sum(p.model == m for p in LAYOUT) for m in range(len(MODELS))}
    assert min(copies.values()) >= 2
    # Each model's five faces are one texture each, shown once per copy.
    assert np.count_nonzero(counts >= 2) >= 5 * len(MODELS)
    assert sorted(counts[counts >= 2].tolist())[-1] == max(copies.values())


def test_same_seed_same_scene_other_seed_other_textures() -> None:
    a, b, c = build_scene("repeated", 0), build_scene("repeated", 0), build_scene("repeated", 1)
    np.testing.assert_array_equal(a.textures[0].levels[0], b.textures[0].levels[0])
    assert not np.array_equal(a.textures[0].levels[0], c.textures[0].levels[0])


def test_repeated_presets_render_with_degraded_queries_only(tmp_path: Path) -> None:
    for name in ("repeated", "repeated-hard"):
        small = dataclasses.replace(PRESETS[name], n_map=2, n_query=2)
        render_dataset(small, tmp_path / name, seed=3, workers=1, progress=False, scale=0.2)
    clean, hard = read_dataset(tmp_path / "repeated"), read_dataset(tmp_path / "repeated-hard")
    assert PRESETS["repeated"].trajectory == PRESETS["repeated-hard"].trajectory == "room"
    assert PRESETS["repeated-hard"].degradation is not None
    for a, b in zip(clean.map_entries, hard.map_entries, strict=True):
        assert (tmp_path / "repeated" / a.image_path).read_bytes() == (
            tmp_path / "repeated-hard" / b.image_path).read_bytes()
    assert any((tmp_path / "repeated" / a.image_path).read_bytes()
               != (tmp_path / "repeated-hard" / b.image_path).read_bytes()
               for a, b in zip(clean.query_entries, hard.query_entries, strict=True))
