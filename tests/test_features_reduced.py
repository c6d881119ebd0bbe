"""SIFT of a reduced image (FeatureConf.scale): keypoints in the full image's pixels."""

import cv2
import numpy as np
import pytest
import skimage.data

from reloc_service.core.errors import ConfigError
from reloc_service.core.features import FeatureConf, extract, match_ratio


@pytest.fixture(scope="module")
def image():
    return cv2.resize(skimage.data.camera(), (640, 480), interpolation=cv2.INTER_AREA)


def test_reduced_keypoints_land_on_the_full_image_ones(image):
    """Keypoints found on the half-size image and mapped back coincide with those full-size
    SIFT finds on the same structure (matched by descriptor) to about a reduced pixel."""
    full = extract(image, FeatureConf("sift", 2000))
    half = extract(image, FeatureConf("sift", 1000, scale=0.5))
    assert 100 < len(half) <= 1000
    q, t, _ = match_ratio(half.descriptors, full.descriptors, ratio=0.7)
    assert len(q) > 0.3 * len(half)
    offsets = np.linalg.norm(half.keypoints_px[q] - full.keypoints_px[t], axis=1)
    assert np.median(offsets) < 1.0  # a reduced pixel is 2 full-image pixels
    # One octave coarser than the same blob found at full size: sizes and levels carry it.
    assert np.median(half.sizes[q] / full.sizes[t]) == pytest.approx(1.0, abs=0.2)
    assert np.all(half.levels >= full.levels.min() + 1)


def test_reduced_keypoints_are_the_small_image_ones_scaled(image):
    small = cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA)
    direct = extract(small, FeatureConf("sift", 500))
    half = extract(image, FeatureConf("sift", 500, scale=0.5))
    assert np.array_equal(half.descriptors, direct.descriptors)
    assert np.allclose(half.keypoints_px, (direct.keypoints_px + 0.5) * 2 - 0.5)


def test_scale_names_its_cache_key_and_is_checked():
    assert FeatureConf("sift").key == "sift"
    assert FeatureConf("sift", scale=0.5).key == "sift@0.5"
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ConfigError, match=r"scale must be in \(0, 1\]"):
            FeatureConf("sift", scale=bad)
