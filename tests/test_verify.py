"""The shared verification: every way a doubtful estimate is refused, and the confidence."""

import numpy as np
import pytest

from reloc_service.algorithms.pose.base import PoseEstimate
from reloc_service.algorithms.relocalizers.base import (
    RelocStatus,
    VerifyConf,
    log10_false_alarms_px,
    position_sigma_m,
    result_from_estimate,
    verify,
)
from reloc_service.core.errors import ConfigError


def estimate(n=100, matches=150, rms=0.8, spread=1.0, cov_sigma=0.01, ncc=None, geometric=True):
    rng = np.random.default_rng(0)
    px = np.column_stack([rng.uniform(0, 640 * spread, n), rng.uniform(0, 480 * spread, n)])
    return PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[3], num_matches=matches,
                        inliers=n if geometric else None, reprojection_rms_px=rms if geometric else None,
                        covariance=np.eye(6) * cov_sigma**2 if geometric else None, ncc=ncc,
                        inlier_px=px, image_size=(640, 480),
                        inlier_threshold_px=5.0 if geometric else None)


def test_good_estimate_accepted_with_confidence():
    ok, reason, confidence = verify(estimate(), VerifyConf())
    assert ok and reason == "" and 0.5 < confidence <= 1.0


@pytest.mark.parametrize("kwargs, words", [
    (dict(n=8), "too few inliers"),
    (dict(n=12, matches=1000), "could be chance"),
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


def test_twelve_spread_inliers_pass_forty_on_one_patch_do_not():
    assert verify(estimate(n=12, matches=30), VerifyConf())[0]
    ok, reason, _ = verify(estimate(n=40, matches=60, spread=0.2), VerifyConf())
    assert not ok and "cover too little" in reason


def test_false_alarms_fall_with_inliers_and_rise_with_matches_and_threshold():
    base = log10_false_alarms_px(100, 20, 5.0, (640, 480))
    assert log10_false_alarms_px(100, 30, 5.0, (640, 480)) < base < -3
    assert log10_false_alarms_px(1000, 20, 5.0, (640, 480)) > base
    assert log10_false_alarms_px(100, 20, 20.0, (640, 480)) > base
    assert log10_false_alarms_px(100, 3, 5.0, (640, 480)) == float("inf")


def test_guided_estimates_are_judged_on_their_unguided_consensus():
    grown = estimate(n=200, matches=1000)
    grown.unguided_evidence = (1000, 12)       # 12 of 1000 before guided matching: chance
    ok, reason, _ = verify(grown, VerifyConf())
    assert not ok and "could be chance (12 of 1000" in reason
    grown.unguided_evidence = (40, 20)
    assert verify(grown, VerifyConf())[0]


def test_derived_rms_gate_follows_the_inlier_threshold():
    est = estimate(rms=3.0)
    assert verify(est, VerifyConf())[0]                 # below 5 / sqrt(2) = 3.54 px
    est.inlier_threshold_px = 3.0                        # gate 2.12 px
    assert "reprojection RMS" in verify(est, VerifyConf())[1]
    assert "reprojection RMS" in verify(estimate(rms=3.0), VerifyConf(max_rms_px=2.0))[1]


@pytest.mark.parametrize("options", [dict(max_false_alarms=0), dict(min_inliers=3),
                                     dict(max_rms_px=-1.0)])
def test_bad_options_rejected(options):
    with pytest.raises(ConfigError):
        VerifyConf(**options)


def test_consensus_bunched_where_chance_agreement_is_likely_is_refused():
    est = estimate(n=14, matches=60)
    assert verify(est, VerifyConf())[0]
    est.chance_probability = 0.05             # keypoints and points crowd one small patch
    ok, reason, _ = verify(est, VerifyConf())
    assert not ok and "could be chance" in reason


def test_inlier_floor_applies_before_guided_matching_too():
    grown = estimate(n=60, matches=80)
    grown.unguided_evidence = (12, 5)
    ok, reason, _ = verify(grown, VerifyConf())
    assert not ok and "before guided matching (5 < 6)" in reason
    grown.unguided_evidence = (12, 8)
    assert verify(grown, VerifyConf())[0]


def _patch_estimate(half_size_m, depth_spread_m=0.0, n=80, sigma_m=0.003, seed=1):
    """Inliers on a square of ``half_size_m`` facing a camera (f 460, 640x480) 2 m away,
    each point pushed off the plane by up to ``depth_spread_m``: pixels and world points."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-half_size_m, half_size_m, (n, 2))
    z = 2.0 + rng.uniform(-depth_spread_m, depth_spread_m, n) + rng.normal(0, sigma_m, n)
    pts = np.column_stack([xy, z])
    px = 460.0 * pts[:, :2] / pts[:, 2:] + [320.0, 240.0]
    est = estimate(n=n, matches=n + 10)
    est.inlier_px, est.inlier_points_world = px, pts
    est.inlier_sigmas_m = np.full(n, sigma_m)
    return est


def test_support_on_one_small_planar_patch_is_refused():
    # A 40 cm print 2 m away fills about 1/12 of the image: a copy of it elsewhere (another
    # poster, a print on a board) would give the same consensus.
    ok, reason, _ = verify(_patch_estimate(0.2), VerifyConf())
    assert not ok and "one small planar patch" in reason


def test_small_support_in_depth_or_planar_support_over_the_image_is_accepted():
    assert verify(_patch_estimate(0.2, depth_spread_m=0.4), VerifyConf())[0]  # a 3-D object
    assert verify(_patch_estimate(1.5), VerifyConf())[0]                       # a whole wall


def test_noisy_plane_is_one_plane_and_a_bump_is_not():
    from reloc_service.algorithms.relocalizers.inlier_coverage import on_one_plane

    rng = np.random.default_rng(2)
    sig = np.full(300, 0.01)
    rejected = 0
    for _ in range(100):
        pts = np.column_stack([rng.uniform(-1, 1, (300, 2)), rng.normal(0, 0.01, 300)])
        rejected += not on_one_plane(pts, sig)
    assert rejected <= 5  # the test's false rejection is 1 %
    pts[:60, 2] += 0.1    # a fifth of the points 10 sigma off the plane
    assert not on_one_plane(pts, sig)


def test_plane_fit_stops_when_the_kept_points_repeat():
    """Refitting on the same points gives the same plane, so stopping there decides as the
    three fixed refits did (that procedure written out here), on planes with outliers."""
    from reloc_service.algorithms.relocalizers.inlier_coverage import (
        _max_outside_3_sigma,
        on_one_plane,
        within_3_sigma_of_plane,
    )

    def three_refits(pts, sig):
        keep = np.ones(len(pts), bool)
        for _ in range(3):
            if keep.sum() < 3:
                return False
            keep = within_3_sigma_of_plane(pts, sig, keep)
        return int(np.count_nonzero(~keep)) <= _max_outside_3_sigma(len(pts), 0.01)

    rng = np.random.default_rng(5)
    decisions = []
    for outliers in (0, 1, 3, 8, 30):
        for _ in range(20):
            pts = np.column_stack([rng.uniform(-1, 1, (120, 2)), rng.normal(0, 0.01, 120)])
            pts[:outliers, 2] += rng.uniform(-0.5, 0.5, outliers)
            sig = np.full(120, 0.01)
            decisions.append(on_one_plane(pts, sig))
            assert decisions[-1] == three_refits(pts, sig)
    assert any(decisions) and not all(decisions)


def test_inlier_spread_is_the_hull_and_skips_only_passing_planes():
    """OpenCV's float32 hull area is scipy's within 1e-6 of the image, so a support spread
    beyond the patch share (with a margin) passes the patch test as the plane fit would."""
    from scipy.spatial import ConvexHull

    from reloc_service.algorithms.relocalizers.inlier_coverage import inlier_spread

    rng = np.random.default_rng(9)
    for _ in range(300):
        n = int(rng.integers(3, 200))
        px = rng.uniform(0, 640, 2) + rng.normal(0, rng.uniform(1, 200), (n, 2))
        est = PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[], num_matches=n, inliers=n,
                           inlier_px=px, image_size=(640, 480))
        assert abs(inlier_spread(est) - ConvexHull(px).volume / (640 * 480)) < 1e-6
    # A small planar patch is still refused; the same plane spread wide is accepted.
    assert not verify(_patch_estimate(0.2), VerifyConf())[0]
    assert verify(_patch_estimate(1.5), VerifyConf())[0]


def test_largest_eigenvalue_in_closed_form_is_lapacks():
    """The position sigma's closed-form eigenvalue equals ``eigvalsh``'s on covariances of
    every shape: random, badly conditioned, tiny and large, diagonal, isotropic with a
    perturbation (a near-triple root), rank-deficient, negative definite."""
    from reloc_service.algorithms.relocalizers.base import largest_eigenvalue_sym3

    rng = np.random.default_rng(4)
    cases = [np.diag([3e-4, 1e-4, 2e-4]), np.eye(3) * 2e-5,
             np.eye(3) * 1e-4 + 1e-19 * np.ones((3, 3)), np.zeros((3, 3)), -np.eye(3),
             np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) * 1e-6]
    for scale in (1e-10, 1e-4, 1.0, 1e3):
        for _ in range(50):
            a = rng.normal(size=(3, 3))
            u = np.linalg.qr(a)[0]
            eig = rng.uniform(0.0, 1.0, 3) ** rng.integers(1, 8)  # condition up to ~1e7
            cases.append(scale * (u * eig) @ u.T)
    for c in cases:
        c = (c + c.T) / 2
        want = np.linalg.eigvalsh(c).max()
        got = largest_eigenvalue_sym3(c.tolist())
        assert abs(got - want) <= 1e-9 * max(np.abs(c).max(), 1e-300), (c, got, want)
    assert position_sigma_m(np.diag([0.04, 0.01, 0.09, 1.0, 1.0, 1.0])) == pytest.approx(0.3)
