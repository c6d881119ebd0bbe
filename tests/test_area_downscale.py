"""The compiled area downscale behind the small blurry image gives OpenCV's INTER_AREA values,
on real photographs and on blocks whose mean lies exactly half-way between two values."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from reloc_service.core import frame
from reloc_service.core.frame import area_downscale

pytest.importorskip("numba")

MINI = Path(__file__).parent / "data" / "tum_fr1_rpy_mini" / "images"


def _images() -> list[np.ndarray]:
    """Real 640x480 photographs (read back from JPEG as the service decodes them), noise,
    and images whose every block sums to k * area + area / 2 (round half to even decides)."""
    out = []
    for path in sorted(p for p in MINI.iterdir() if p.suffix in (".png", ".jpg"))[:4]:
        ok, jpeg = cv2.imencode(".jpg", cv2.imread(str(path), cv2.IMREAD_GRAYSCALE),
                                [cv2.IMWRITE_JPEG_QUALITY, 90])
        out.append(cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE))
    rng = np.random.default_rng(2)
    out.append(rng.integers(0, 256, (480, 640), dtype=np.uint8))
    for base in (6, 7, 200, 201):  # even and odd means, each exactly half-way up
        half = np.full((480, 640), base, np.uint8)
        half[::2, ::2] += 1  # a quarter of a block at +1 ...
        half[1::2, ::2] += 1  # ... and another quarter: sum = base * area + area / 2
        out.append(half)
    assert out[0].shape == (480, 640)
    return out


@pytest.mark.parametrize("factor", [4, 8, 16, 32])
def test_compiled_downscale_is_opencvs_inter_area(factor, monkeypatch):
    images = _images()
    expected = [cv2.resize(im, (640 // factor, 480 // factor), interpolation=cv2.INTER_AREA)
                for im in images]

    def no_opencv(*args, **kwargs):
        raise AssertionError("the compiled path should have served this size")

    monkeypatch.setattr(frame.cv2, "resize", no_opencv)
    for image, want in zip(images, expected, strict=True):
        assert np.array_equal(area_downscale(image, 640 // factor, 480 // factor), want)


def test_other_sizes_and_factors_give_opencvs_values_too():
    image = np.random.default_rng(3).integers(0, 256, (480, 752), dtype=np.uint8)
    for size in ((40, 30), (376, 240), (94, 60)):  # 18.8x, 2x (OpenCV), 8x (compiled)
        assert np.array_equal(area_downscale(image, *size),
                              cv2.resize(image, size, interpolation=cv2.INTER_AREA))
