"""SIFT of a reduced image (FeatureConf.scale): keypoints in the full image's pixels."""

import cv2
import numpy as np
import pytest
import skimage.data

from reloc_service.core.errors import ConfigError
from reloc_service.core.features import (
    SIFT_UPSCALE_OFFSET_PX,
    FeatureConf,
    extract,
    match_ratio,
)


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
    off = SIFT_UPSCALE_OFFSET_PX
    assert np.allclose(half.keypoints_px, (direct.keypoints_px - off + 0.5) * 2 - 0.5 + off)


def _blobs(rng, size_px, count=40, shape=(480, 640)):
    """An image of Gaussian blobs of 1-sigma ``size_px`` at random sub-pixel centres (pixel
    ``i`` covering ``[i - 0.5, i + 0.5]``), and those centres."""
    h, w = shape
    centres = np.column_stack([rng.uniform(40, w - 40, count), rng.uniform(40, h - 40, count)])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.full(shape, 60.0)
    for x0, y0 in centres:
        img += 150 * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * size_px ** 2))
    return np.clip(img, 0, 255).astype(np.uint8), centres


def _mean_offset(feats, centres, radius_px):
    """Mean of (found - true) over the centres with a keypoint within ``radius_px``."""
    d = feats.keypoints_px[None, :, :] - centres[:, None, :]
    nearest = np.linalg.norm(d, axis=2).argmin(axis=1)
    found = d[np.arange(len(centres)), nearest]
    return found[np.linalg.norm(found, axis=1) < radius_px].mean(axis=0)


def test_sift_offset_is_measured_and_the_reduced_image_shares_it():
    """Full-size SIFT reports blobs +0.25 px off their centres (its upsampled first octave);
    the half-size image's keypoints, mapped back, carry the same offset, not twice it, so
    matching them against landmarks made from full-size keypoints adds no common shift."""
    rng = np.random.default_rng(0)
    full, half = [], []
    for _ in range(4):
        img, centres = _blobs(rng, 3.0)
        full.append(_mean_offset(extract(img, FeatureConf("sift", 2000)), centres, 1.5))
        img, centres = _blobs(rng, 6.0)
        half.append(_mean_offset(extract(img, FeatureConf("sift", 1000, scale=0.5)),
                                 centres, 3.0))
    full_offset, half_offset = np.mean(full, axis=0), np.mean(half, axis=0)
    assert np.allclose(full_offset, SIFT_UPSCALE_OFFSET_PX, atol=0.02)
    assert np.allclose(half_offset, full_offset, atol=0.1)  # 0.5 px without the correction


def test_scale_names_its_cache_key_and_is_checked():
    assert FeatureConf("sift").key == "sift"
    assert FeatureConf("sift", scale=0.5).key == "sift@0.5"
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ConfigError, match=r"scale must be in \(0, 1\]"):
            FeatureConf("sift", scale=bad)
