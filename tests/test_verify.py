"""The shared verification: every way a doubtful estimate is refused, and the confidence."""

import numpy as np
import pytest

from reloc_service.pose.base import PoseEstimate
from reloc_service.relocalizers.base import RelocStatus, VerifyConf, result_from_estimate, verify


def estimate(n=100, matches=150, rms=0.8, spread=1.0, cov_sigma=0.01, ncc=None, geometric=True):
    rng = np.random.default_rng(0)
    px = np.column_stack([rng.uniform(0, 640 * spread, n), rng.uniform(0, 480 * spread, n)])
    return PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[3], num_matches=matches,
                        inliers=n if geometric else None, reprojection_rms_px=rms if geometric else None,
                        covariance=np.eye(6) * cov_sigma**2 if geometric else None, ncc=ncc,
                        inlier_px=px, image_size=(640, 480))


def test_good_estimate_accepted_with_confidence():
    ok, reason, confidence = verify(estimate(), VerifyConf())
    assert ok and reason == "" and 0.5 < confidence <= 1.0


@pytest.mark.parametrize("kwargs, words", [
    (dict(n=10), "too few inliers"),
    (dict(n=30, matches=1000), "inlier ratio"),
    (dict(rms=4.0), "reprojection RMS"),
    (dict(spread=0.2), "cover too little"),
    (dict(cov_sigma=0.5), "too uncertain"),
    (dict(geometric=False, ncc=0.5), "alignment too weak"),
])
def test_refusals_name_their_reason(kwargs, words):
    ok, reason, confidence = verify(estimate(**kwargs), VerifyConf())
    assert not ok and words in reason and confidence == 0.0


def test_confidence_grows_with_evidence():
    weak = verify(estimate(n=25, rms=2.0), VerifyConf())[2]
    strong = verify(estimate(n=300, matches=320, rms=0.5), VerifyConf())[2]
    assert 0 < weak < strong


def test_none_and_nan_refused():
    assert verify(None, VerifyConf())[:2] == (False, "no pose hypothesis")
    bad = estimate()
    bad.world_from_cam = np.full((4, 4), np.nan)
    assert not verify(bad, VerifyConf())[0]


def test_result_carries_evidence():
    res = result_from_estimate(estimate(), VerifyConf(), method="sbi+p3p", map_version=7,
                               timings={"solve": 0.001})
    assert res.status is RelocStatus.OK and res.inliers == 100 and res.map_version == 7
    assert res.matched_keyframe_ids == [3] and res.covariance.shape == (6, 6)
    refused = result_from_estimate(estimate(n=5), VerifyConf(), method="sbi+p3p", map_version=7,
                                   timings={})
    assert refused.world_from_cam is None and "too few inliers" in refused.reason
