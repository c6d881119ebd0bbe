"""ORB keypoints spread over a grid (FeatureConf.grid): same kind and count per level, more
of the image covered where the texture clusters."""

import cv2
import numpy as np
import pytest
import skimage.data

from reloc_service.core.errors import ConfigError
from reloc_service.core.features import (
    FeatureConf,
    extract,
    match_ratio,
    orb_level_quota,
    spread_over_grid,
)


@pytest.fixture(scope="module")
def clustered():
    """A 640x480 image textured in its top-left quarter only, with a faint texture elsewhere:
    the strongest corners all lie in one quarter, weaker ones everywhere."""
    rng = np.random.default_rng(0)
    faint = cv2.GaussianBlur(rng.integers(0, 255, (480, 640)).astype(np.uint8), (0, 0), 2.0)
    image = (128 + (faint.astype(np.float64) - 128) * 0.6).astype(np.uint8)
    image[:240, :320] = cv2.resize(skimage.data.camera(), (320, 240))
    return image


def _cells(points_px, grid=4, shape=(480, 640)):
    h, w = shape
    c = (np.minimum(points_px[:, 1] * grid // h, grid - 1) * grid
         + np.minimum(points_px[:, 0] * grid // w, grid - 1)).astype(int)
    return np.bincount(c, minlength=grid * grid)


def _in_textured(feats):
    """Share of the keypoints in the textured top-left quarter."""
    return np.mean((feats.keypoints_px[:, 0] < 320) & (feats.keypoints_px[:, 1] < 240))


def test_spread_keeps_each_level_count_and_covers_more_cells(clustered):
    plain = extract(clustered, FeatureConf("orb", 500))
    spread = extract(clustered, FeatureConf("orb", 500, grid=4))
    assert len(spread) == len(plain) == 500
    assert np.array_equal(np.bincount(spread.levels, minlength=8), orb_level_quota(500))
    assert _in_textured(plain) > 0.9
    assert _in_textured(spread) < _in_textured(plain) - 0.1
    assert (_cells(spread.keypoints_px) > 0).sum() > (_cells(plain.keypoints_px) > 0).sum()


def test_spread_descriptors_describe_their_keypoints(clustered):
    """Each kept keypoint's descriptor is the one plain ORB computes at that keypoint."""
    spread = extract(clustered, FeatureConf("orb", 300, grid=4))
    again = extract(clustered, FeatureConf("orb", 300, grid=4))
    assert np.array_equal(spread.keypoints_px, again.keypoints_px)
    q, t, _ = match_ratio(spread.descriptors, again.descriptors)
    assert len(q) > 0.9 * len(spread) and np.all(q == t)


def test_spread_over_grid_fills_cells_first_then_the_strongest():
    # 2x2 grid of a 10x10 image, one level of quota 4: cell (0, 0) holds the three strongest
    # keypoints, each other cell one weak one; each cell's share (1) is kept first, then the
    # strongest remaining.
    pts = np.array([[1, 1], [2, 2], [3, 3], [8, 1], [1, 8], [8, 8]], np.float64)
    response = np.array([9.0, 8.0, 7.0, 1.0, 2.0, 3.0])
    kept = spread_over_grid(pts, np.zeros(6, np.int64), response, (10, 10), grid=2,
                            level_quota=np.array([5]))
    assert kept.tolist() == [0, 1, 3, 4, 5]
    kept = spread_over_grid(pts, np.zeros(6, np.int64), response, (10, 10), grid=1,
                            level_quota=np.array([2]))
    assert kept.tolist() == [0, 1]


def test_orb_level_quota_sums_to_the_count():
    quota = orb_level_quota(500)
    assert quota.sum() == 500 and np.all(np.diff(quota) <= 0)


def test_grid_conf_errors_and_key():
    assert FeatureConf("orb", 500, grid=4).key == "orb#4"
    assert FeatureConf("orb", 500).key == "orb"
    with pytest.raises(ConfigError, match="grid"):
        FeatureConf("sift", 500, grid=4)
    with pytest.raises(ConfigError, match="grid"):
        FeatureConf("orb", 500, grid=0)


def test_p3p_query_grid_names_and_extracts_spread_features(clustered):
    """The pose finder's ``query_grid`` reaches the extraction, under its own cache key, and
    is refused for SIFT."""
    from reloc_service.algorithms.pose import p3p  # noqa: F401 (registers "p3p")
    from reloc_service.algorithms.pose.base import create_pose_finder

    finder = create_pose_finder({"name": "p3p", "kind": "orb", "max_features": 500,
                                 "query_grid": 4})
    (key, conf), = finder.feature_confs().items()
    assert key == "orb#4" and conf.grid == 4
    spread = extract(clustered, FeatureConf("orb", 500, grid=4))
    assert np.array_equal(extract(clustered, conf).keypoints_px, spread.keypoints_px)
    with pytest.raises(ConfigError, match="grid"):
        create_pose_finder({"name": "p3p", "kind": "sift", "query_grid": 4})
