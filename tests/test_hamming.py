from pathlib import Path

import cv2
import numpy as np
import pytest

from reloc_service.core import hamming
from reloc_service.core.features import FeatureConf, extract

MINI = Path(__file__).parent / "data" / "tum_fr1_rpy_mini" / "images"


def _orb_of_jpeg(path: Path) -> np.ndarray:
    """500 ORB descriptors of a real photograph, read back from its JPEG encoding."""
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    decoded = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE)
    return extract(decoded, FeatureConf("orb", 500)).descriptors


@pytest.fixture(scope="module")
def real_pair():
    images = sorted(p for p in MINI.iterdir() if p.suffix in (".png", ".jpg"))
    assert len(images) >= 2, f"expected the TUM mini fixture's images in {MINI}"
    return _orb_of_jpeg(images[0]), _orb_of_jpeg(images[1])


def _reference(a, b):
    """Two nearest by (distance, index) from the full matrix: the definition."""
    full = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)
    order = np.lexsort((np.broadcast_to(np.arange(len(b)), full.shape), full), axis=1)[:, :2]
    return np.take_along_axis(full, order, 1).astype(np.float32), order


def test_numpy_path_is_the_definition_on_real_orb(real_pair):
    a, b = real_pair
    dist, idx = hamming.knn2(a, b, compiled=False)
    ref_d, ref_i = _reference(a, b)
    assert np.array_equal(dist, ref_d) and np.array_equal(idx, ref_i)


def test_compiled_path_gives_the_numpy_answers(real_pair):
    """The [jit] kernel and numpy agree to the bit, on real descriptors and on rows full of
    ties (few distinct descriptors: the earlier row must win, as argmin's)."""
    pytest.importorskip("numba")
    a, b = real_pair
    rng = np.random.default_rng(0)
    few = a[:4]
    cases = [(a, b), (b, a), (few[rng.integers(0, 4, 60)], few[rng.integers(0, 4, 90)]),
             (a[:1], b[:2]), (a[:, :12], b[:, :12])]
    for qa, qb in cases:
        np_d, np_i = hamming.knn2(qa, qb, compiled=False)
        jit_d, jit_i = hamming.knn2(qa, qb, compiled=True)
        assert np.array_equal(np_d, jit_d) and np.array_equal(np_i, jit_i)
    ties = hamming.knn2(*cases[2][:2], compiled=True)
    assert np.all(ties[0][:, 0] == 0)  # every query row has an identical train row


def test_compiled_path_without_numba_says_how_to_get_it(monkeypatch):
    monkeypatch.setattr(hamming, "compiled_knn2", lambda: None)
    a = np.zeros((2, 32), np.uint8)
    with pytest.raises(ImportError, match="jit"):
        hamming.knn2(a, a, compiled=True)
    assert hamming.knn2(a, a)[0].shape == (2, 2)  # None: falls back to numpy


def test_compiled_path_on_wider_descriptors_than_orb(real_pair):
    """Descriptors of more than 4 words (64 and 40 bytes: two ORB rows side by side, cut)
    pass through the kernel's 4-word steps, zero-padded, with the numpy answers."""
    pytest.importorskip("numba")
    a, b = real_pair
    wide_a, wide_b = np.hstack([a, a[::-1]]), np.hstack([b, b[::-1]])
    for qa, qb in ((wide_a, wide_b), (wide_a[:, :40], wide_b[:, :40])):
        np_d, np_i = hamming.knn2(qa, qb, compiled=False)
        jit_d, jit_i = hamming.knn2(qa, qb, compiled=True)
        assert np.array_equal(np_d, jit_d) and np.array_equal(np_i, jit_i)
        assert np.array_equal(jit_d, _reference(qa, qb)[0])
