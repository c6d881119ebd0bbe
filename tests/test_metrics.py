"""Evaluation metrics on hand-made numbers."""

import math

import numpy as np
import pytest

from reloc_service.tools.eval import metrics

NAN = math.nan
# Six queries: four returned, two not (their errors are NaN).
T = [0.01, 0.20, 0.40, 0.90, NAN, NAN]  # metres
R = [1.0, 12.0, 3.0, 2.0, NAN, NAN]  # degrees
OK = [True, True, True, True, False, False]


def test_recall_counts_only_returned_poses_within_both_thresholds():
    assert metrics.recall(T, R, OK, 0.05, 5.0) == pytest.approx(1 / 6)
    # 0.20 m passes 25 cm but 12 deg fails 10 deg; 0.40 m fails 25 cm.
    assert metrics.recall(T, R, OK, 0.25, 10.0) == pytest.approx(1 / 6)
    # 50 cm / 15 deg: 0.01, 0.20 (12 deg <= 15), 0.40 pass; 0.90 m fails.
    assert metrics.recall(T, R, OK, 0.50, 15.0) == pytest.approx(3 / 6)


def test_recall_thresholds_are_inclusive():
    assert metrics.recall([0.05], [5.0], [True], 0.05, 5.0) == 1.0
    assert metrics.recall([0.0501], [5.0], [True], 0.05, 5.0) == 0.0


def test_recalls_keys():
    got = metrics.recalls(T, R, OK)
    assert list(got) == ["5cm_5deg", "25cm_10deg", "50cm_15deg"]
    assert got["50cm_15deg"] == pytest.approx(0.5)


def test_wrong_rate_is_fraction_of_all_queries():
    # Only the 0.90 m pose is wrong.
    assert metrics.wrong_rate(T, R, OK) == pytest.approx(1 / 6)
    assert metrics.wrong_mask(T, R, OK).tolist() == [False, False, False, True, False, False]
    # A rotation beyond 15 deg alone makes a pose wrong.
    assert metrics.wrong_rate([0.01], [16.0], [True]) == 1.0


def test_not_relocalized_rate():
    assert metrics.not_relocalized_rate(OK) == pytest.approx(2 / 6)
    assert math.isnan(metrics.not_relocalized_rate([]))


def test_rates_partition_the_queries():
    within_wrong = metrics.recall(T, R, OK, 0.5, 15.0) + metrics.wrong_rate(T, R, OK)
    assert within_wrong + metrics.not_relocalized_rate(OK) == pytest.approx(1.0)


def test_median_errors_over_returned_only():
    med_t, med_r = metrics.median_errors(T, R, OK)
    assert med_t == pytest.approx((0.20 + 0.40) / 2)
    assert med_r == pytest.approx((2.0 + 3.0) / 2)
    assert all(math.isnan(v) for v in metrics.median_errors([NAN], [NAN], [False]))


def test_percentile_ignores_nan_and_interpolates():
    values = [10.0, 20.0, NAN, 30.0, 40.0]
    assert metrics.percentile(values, 50) == pytest.approx(25.0)
    assert metrics.percentile(values, 99) == pytest.approx(30.0 + 0.97 * 10.0)
    assert math.isnan(metrics.percentile([], 50))


def test_returned_pose_with_nan_error_is_rejected():
    with pytest.raises(ValueError, match="non-finite"):
        metrics.recall([NAN], [1.0], [True], 0.05, 5.0)
    with pytest.raises(ValueError, match="length"):
        metrics.recall([0.1, 0.2], [1.0], [True], 0.05, 5.0)


def test_closest_ranks_by_hand():
    keyframes = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    queries = np.array([[0.1, 0, 0],   # order 0, 1, 2, 3
                        [2.2, 0, 0],   # order 2, 3, 1, 0
                        [1.5, 0, 0],   # 1 and 2 tie at 0.5
                        [0.0, 5, 0]])
    chosen = [0, 1, 2, -1]
    assert metrics.closest_ranks(queries, keyframes, chosen).tolist() == [1, 3, 1, 0]
    assert metrics.closest_ranks(queries, keyframes, [3, 0, 1, 0]).tolist() == [4, 4, 1, 1]


def test_closest_ranks_checks_indices():
    with pytest.raises(ValueError, match="expected -1 or a row"):
        metrics.closest_ranks(np.zeros((1, 3)), np.zeros((2, 3)), [2])
    with pytest.raises(ValueError, match="one per query"):
        metrics.closest_ranks(np.zeros((2, 3)), np.zeros((2, 3)), [0])


def test_rank_histogram_skips_zero():
    assert metrics.rank_histogram([1, 1, 2, 0, 5, 1]) == {1: 3, 2: 1, 5: 1}
    assert metrics.rank_histogram([]) == {}


def test_threshold_key():
    assert metrics.threshold_key(0.05, 5.0) == "5cm_5deg"
    assert metrics.threshold_key(0.25, 10) == "25cm_10deg"


def test_chi3_median_is_scipys():
    stats = pytest.importorskip("scipy.stats")
    assert metrics.CHI3_MEDIAN == pytest.approx(math.sqrt(stats.chi2.ppf(0.5, 3)), rel=1e-12)


@pytest.mark.parametrize("inflation", [1.0, 2.0, 0.5])
def test_covariance_scale_recovers_how_far_the_stated_sigmas_are_off(inflation):
    """Errors drawn from an anisotropic, rotated covariance, scored against that covariance
    scaled: the scale says how many times the stated sigmas must grow to fit the errors."""
    rng = np.random.default_rng(7)
    from reloc_service.core.geometry import se3_exp

    est = se3_exp([0.3, -0.2, 1.0, 0.4, -0.7, 0.2])
    a = rng.normal(size=(3, 3))
    cov_t = a @ a.T * 1e-4 + np.diag([1e-6, 4e-6, 9e-6])
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = cov_t / inflation**2
    covariance[3:, 3:] = np.eye(3) * 1e-6
    rho = rng.multivariate_normal(np.zeros(3), cov_t, size=4000)
    distances = []
    for r in rho:
        gt = est.copy()
        gt[:3, 3] = est[:3, 3] + est[:3, :3] @ r  # the right perturbation, to first order
        distances.append(metrics.translation_mahalanobis(est, gt, covariance))
    scale = metrics.covariance_scale(distances, np.ones(len(distances), bool))
    assert scale == pytest.approx(inflation, rel=0.05)


def test_chi3_beyond_3_is_scipys():
    stats = pytest.importorskip("scipy.stats")
    assert metrics.CHI3_BEYOND_3 == pytest.approx(stats.chi2.sf(9.0, 3), rel=1e-12)


def test_tail_share_and_rms_scale_of_gaussian_and_heavy_tailed_errors():
    """Gaussian errors under their own covariance: 2.9 % beyond 3 sigma and a second-moment
    scale of 1. Errors from a multivariate t with 5 degrees of freedom, scaled so that their
    median length is the Gaussian's: the median scale stays 1 while the tail share and the
    second-moment scale show the heavy tail (t5's second moment is 5/3 of its scale's)."""
    rng = np.random.default_rng(11)
    n = 20000
    gauss = np.linalg.norm(rng.normal(size=(n, 3)), axis=1)
    ok = np.ones(n, bool)
    assert metrics.beyond_sigma_share(gauss, ok) == pytest.approx(metrics.CHI3_BEYOND_3, abs=0.004)
    assert metrics.covariance_rms_scale(gauss, ok) == pytest.approx(1.0, abs=0.02)
    t5 = gauss / np.sqrt(rng.chisquare(5, n) / 5)
    t5 *= metrics.CHI3_MEDIAN / np.median(t5)
    assert metrics.covariance_scale(t5, ok) == pytest.approx(1.0, abs=1e-9)
    assert metrics.beyond_sigma_share(t5, ok) > 2 * metrics.CHI3_BEYOND_3
    assert metrics.covariance_rms_scale(t5, ok) > 1.15


def test_tail_share_and_rms_scale_skip_unreturned_and_count_infinite():
    lengths = [1.0, 4.0, math.nan, 10.0]
    returned = [True, True, True, False]
    assert metrics.beyond_sigma_share(lengths, returned) == pytest.approx(0.5)
    assert metrics.covariance_rms_scale(lengths, returned) == pytest.approx(math.sqrt(17 / 6))
    assert metrics.beyond_sigma_share([1.0, math.inf], [True, True]) == pytest.approx(0.5)
    assert metrics.covariance_rms_scale([1.0, math.inf], [True, True]) == math.inf
    assert math.isnan(metrics.beyond_sigma_share([2.0], [False]))
    assert math.isnan(metrics.covariance_rms_scale([math.nan], [True]))


def test_covariance_scale_skips_unreturned_and_singular():
    singular = np.zeros((6, 6))
    assert metrics.translation_mahalanobis(np.eye(4), np.eye(4), singular) == math.inf
    nan_cov = np.full((6, 6), np.nan)
    assert metrics.translation_mahalanobis(np.eye(4), np.eye(4), nan_cov) == math.inf
    assert metrics.covariance_scale([1.0, math.inf, 5.0], [True, True, False]) == pytest.approx(
        1.0 / metrics.CHI3_MEDIAN)
    assert math.isnan(metrics.covariance_scale([math.nan], [False]))


@pytest.mark.parametrize("n", [5, 10, 22, 69])
def test_covariance_scale_interval_holds_the_true_scale_as_often_as_it_says(n):
    """Honest errors (chi with 3 degrees of freedom, true scale 1) in 2000 sets of n answers:
    the interval holds 1 at least as often as its stated coverage (exact for the median's
    order statistics), and it narrows as answers accumulate."""
    rng = np.random.default_rng(n)
    held, widths = 0, []
    for _ in range(2000):
        d = np.sqrt(rng.chisquare(3, n))
        low, high, coverage = metrics.covariance_scale_interval(d, np.ones(n, bool))
        assert low <= metrics.covariance_scale(d, np.ones(n, bool)) <= high
        held += low <= 1.0 <= high
        widths.append(high - low)
    if n == 5:   # 95 % is out of reach: the extremes, which hold the median 15 times in 16
        assert coverage == pytest.approx(1 - 2 / 2**5)
    else:
        assert coverage >= 0.95
    # Binomial noise of the count over 2000 sets: 3 sigma below the stated coverage.
    assert held / 2000 >= coverage - 3 * math.sqrt(coverage * (1 - coverage) / 2000)
    assert np.median(widths) < (2.0 if n == 5 else 1.0)


def test_covariance_scale_interval_uses_only_returned_finite_answers():
    low, high, coverage = metrics.covariance_scale_interval(
        [1.0, 2.0, math.nan, 3.0, 4.0, 5.0, 100.0], [True, True, True, True, True, True, False])
    assert (low, high) == pytest.approx((1.0 / metrics.CHI3_MEDIAN, 5.0 / metrics.CHI3_MEDIAN))
    assert coverage == pytest.approx(1 - 2 / 2**5)
    assert all(math.isnan(x) for x in metrics.covariance_scale_interval([math.nan], [True]))
    assert all(math.isnan(x) for x in metrics.covariance_scale_interval([1.0], [False]))


def test_covariance_scale_interval_needs_two_answers():
    """One length would be an interval of zero width, holding the median with probability 0:
    none is given. Two are their extremes, holding it half the time."""
    assert all(math.isnan(x) for x in metrics.covariance_scale_interval([2.0], [True]))
    assert all(math.isnan(x) for x in metrics.covariance_scale_interval(
        [2.0, math.nan, 3.0], [True, True, False]))
    low, high, coverage = metrics.covariance_scale_interval([1.0, 2.0], [True, True])
    assert (low, high) == pytest.approx((1.0 / metrics.CHI3_MEDIAN, 2.0 / metrics.CHI3_MEDIAN))
    assert coverage == pytest.approx(0.5)
