"""Tests of the random-ferns classifier (sparse counts) and its warped training samples."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from reloc_service.algorithms.ferns.classifier import FernClassifier
from reloc_service.algorithms.ferns.fern_tests import FernConf
from reloc_service.algorithms.ferns.training import (
    WarpConf,
    draw_warps,
    extract_patches,
    prepare_image,
    sample_leaves,
)
from reloc_service.core.errors import ConfigError

WARPS = WarpConf(num_warps=40, max_rotation_rad=0.5, min_scale=0.8, max_scale=1.25, seed=3)


@pytest.fixture(scope="module")
def photo() -> np.ndarray:
    return skimage.data.camera()


@pytest.fixture(scope="module")
def centres(photo: np.ndarray) -> np.ndarray:
    """40 distinct SIFT keypoints away from the border."""
    pts = cv2.KeyPoint.convert(cv2.SIFT.create().detect(photo, None)).astype(np.float64)
    pts = np.unique(np.rint(pts), axis=0)
    pts = pts[(pts > 40).all(1) & (pts < 470).all(1)]
    return pts[np.random.default_rng(0).choice(len(pts), 40, replace=False)]


def _table(clf: FernClassifier) -> tuple[np.ndarray, ...]:
    return (*clf.count_table(), clf.class_ids, clf.class_counts)


def _same(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_conf_is_validated() -> None:
    with pytest.raises(ConfigError):
        FernConf(num_tests=17)
    with pytest.raises(ConfigError):
        FernConf(num_ferns=0)
    with pytest.raises(ConfigError):
        WarpConf(min_scale=2.0, max_scale=1.0)


def test_leaves_from_patches_equal_leaves_read_in_the_image() -> None:
    rng = np.random.default_rng(0)
    image = rng.random((90, 120)).astype(np.float32)
    points = np.column_stack([rng.uniform(0, 119, 50), rng.uniform(0, 89, 50)])  # also borders
    clf = FernClassifier(FernConf(num_ferns=20, num_tests=9, patch_size=32))
    from_patches = clf.leaves_from_patches(extract_patches(image, points, 32))
    inner = ((points >= 17) & (points <= [102, 72])).all(1)  # reflect vs replicate differ outside
    np.testing.assert_array_equal(from_patches[inner], clf.leaves_at(image, points)[inner])
    assert clf.leaves_at(image, points).max() < 2**9


def test_first_test_is_the_top_bit() -> None:
    clf = FernClassifier(FernConf(num_ferns=1, num_tests=3, patch_size=8, seed=1))
    patch = np.zeros((1, 8, 8), np.float32)
    yb, xb = clf.off_b[0] + 4   # second pixel of test 0 of fern 0
    patch[0, yb, xb] = 1.0                                     # I(a) < I(b): bit set
    leaf = int(clf.leaves_from_patches(patch)[0, 0])
    assert leaf >> 2 == 1


def test_sparse_scores_equal_the_dense_formula() -> None:
    """Eq. 3.22/3.23 computed with a dense table equals the sparse scoring."""
    rng = np.random.default_rng(1)
    conf = FernConf(num_ferns=3, num_tests=4, regularization=1.0)
    clf = FernClassifier(conf)
    leaves = rng.integers(0, 16, (200, 3)).astype(np.uint16)
    labels = rng.choice([5, 9, 40, 41], 200)
    clf.add(leaves, labels)
    ids = clf.class_ids
    cols = np.array([list(ids).index(x) for x in labels])
    dense = np.zeros((3, 16, 4))
    for m in range(3):
        np.add.at(dense[m], (leaves[:, m], cols), 1)
    n_c = np.array([(labels == c).sum() for c in ids])
    prob = (dense + 1.0) / (n_c + 16 * 1.0)
    probe = rng.integers(0, 16, (30, 3))
    expected = np.log(prob[np.arange(3)[None, :], probe]).sum(1)
    np.testing.assert_allclose(clf.scores(probe.astype(np.uint16)), expected, rtol=1e-5, atol=1e-5)


def _reference_classify(clf: FernClassifier, leaves: np.ndarray, k: int
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Top-k labels and posteriors from the dense formula (eq. 3.22/3.23, float64)."""
    m_ferns, num_leaves = clf.num_ferns, clf.num_leaves
    fern, leaf, label, count = clf.count_table()
    column = {int(c): i for i, c in enumerate(clf.class_ids)}
    col = np.array([column[int(x)] for x in label], np.int64)
    dense = np.zeros((m_ferns, num_leaves, clf.num_classes))
    dense[fern, leaf, col] = count
    nr = clf.conf.regularization
    logp = np.log((dense + nr) / (clf.class_counts + num_leaves * nr))
    scores = logp[np.arange(m_ferns)[None, :], leaves.astype(np.int64)].sum(1)
    post = np.exp(scores - scores.max(1, keepdims=True))
    post /= post.sum(1, keepdims=True)
    top = np.argsort(-scores, axis=1, kind="stable")[:, :k]
    return clf.class_ids[top], np.take_along_axis(post, top, 1)


@pytest.mark.parametrize("compiled", [False, True])
def test_fast_scoring_equals_the_dense_reference(compiled: bool,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Both scoring paths (numpy in blocks of patches; the compiled one-pass kernel) give the
    dense reference's top classes and posteriors, with and without a class mask; the numpy
    path's output does not depend on its block size."""
    from reloc_service.algorithms.ferns import kernels
    from reloc_service.algorithms.ferns import scorer as module

    if compiled and kernels.compiled_classify_rows() is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(5)
    clf = FernClassifier(FernConf(num_ferns=12, num_tests=7, regularization=0.5))
    num_classes = 150
    # Skewed leaves (some frequent, as on real patches) and skewed class sizes.
    train = np.minimum(rng.geometric(0.05, (6000, 12)) - 1, 127).astype(np.uint16)
    weights = np.arange(1, num_classes + 1, dtype=np.float64)
    clf.add(train, rng.choice(np.arange(num_classes) * 7 + 3, 6000, p=weights / weights.sum()))
    probe = np.minimum(rng.geometric(0.05, (333, 12)) - 1, 127).astype(np.uint16)
    scorer = clf.scorer()
    got = scorer._classify(probe, 3, None, compiled=compiled)
    want_labels, want_post = _reference_classify(clf, probe, 3)
    np.testing.assert_array_equal(got[0], want_labels)
    np.testing.assert_allclose(got[1], want_post, rtol=1e-4, atol=1e-6)
    # A mask leaving some patches' best classes out, and fewer allowed classes than k.
    for allowed in (np.arange(clf.num_classes) % 3 == 0, np.arange(clf.num_classes) == 4):
        labels, post = scorer._classify(probe, 3, allowed, compiled=compiled)
        masked = np.where(allowed[None, :], scorer.scores(probe), -np.inf)
        order = np.argsort(-masked, axis=1, kind="stable")[:, :3]
        np.testing.assert_array_equal(labels, clf.class_ids[order])
        assert np.all(post[:, int(allowed.sum()):] == 0)
    if not compiled:
        monkeypatch.setattr(module, "SCORE_BLOCK_FLOATS", 40 * num_classes)  # 9 blocks
        blocked = scorer._classify(probe, 3, None, compiled=False)
        np.testing.assert_array_equal(blocked[0], got[0])
        np.testing.assert_array_equal(blocked[1], got[1])


def test_posteriors_are_normalised_and_best_first() -> None:
    rng = np.random.default_rng(2)
    clf = FernClassifier(FernConf(num_ferns=10, num_tests=6))
    clf.add(rng.integers(0, 64, (300, 10)).astype(np.uint16), rng.integers(0, 7, 300))
    labels, post = clf.classify(rng.integers(0, 64, (20, 10)).astype(np.uint16), top_k=7)
    assert labels.shape == (20, 7) and post.shape == (20, 7)
    np.testing.assert_allclose(post.sum(1), 1.0, rtol=1e-4)
    assert np.all(np.diff(post, axis=1) <= 1e-7)
    allowed = clf.class_ids == 3
    labels, post = clf.classify(rng.integers(0, 64, (5, 10)).astype(np.uint16), top_k=2,
                                allowed=allowed)
    assert np.all(labels[:, 0] == 3) and np.allclose(post[:, 0], 1.0) and np.all(post[:, 1] == 0)


def test_samples_do_not_depend_on_the_batch(photo: np.ndarray, centres: np.ndarray) -> None:
    """Regenerating the samples of a subset of keypoints gives the same leaves (exact removal)."""
    clf = FernClassifier(FernConf(num_ferns=20, num_tests=10))
    warps = draw_warps(WARPS, key=7)
    all_leaves = sample_leaves(clf, photo, centres, warps, WARPS)
    some = sample_leaves(clf, photo, centres[5:9], draw_warps(WARPS, key=7), WARPS)
    np.testing.assert_array_equal(all_leaves[:, 5:9], some)
    other = sample_leaves(clf, photo, centres[5:9], draw_warps(WARPS, key=8), WARPS)
    assert not np.array_equal(other, some)


def test_identity_warp_equals_the_query_path(photo: np.ndarray, centres: np.ndarray) -> None:
    """Warp 0 is the real view, seen exactly as a query sees it."""
    clf = FernClassifier(FernConf(num_ferns=20, num_tests=10))
    leaves = sample_leaves(clf, photo, centres, draw_warps(WARPS, key=0), WARPS)
    query = clf.leaves_at(prepare_image(photo, WARPS.smoothing_sigma), centres)
    np.testing.assert_array_equal(leaves[0], query)  # (away from the border: same padding)


def test_classifier_recognises_warped_patches(photo: np.ndarray, centres: np.ndarray) -> None:
    clf = FernClassifier(FernConf(num_ferns=30, num_tests=10))
    labels = np.arange(len(centres)) * 10 + 1000
    train = sample_leaves(clf, photo, centres, draw_warps(WARPS, key=0), WARPS)
    clf.add(train.reshape(-1, 30), np.tile(labels, len(train)))
    test_conf = WarpConf(**{**WARPS.__dict__, "num_warps": 20, "include_identity": False})
    test = sample_leaves(clf, photo, centres, draw_warps(test_conf, key=1), test_conf)
    truth = np.tile(labels, len(test))
    rate = (clf.predict(test.reshape(-1, 30)) == truth).mean()
    assert rate > 0.85, rate
    one_fern = (clf.first_ferns(1).predict(test.reshape(-1, 30)[:, :1]) == truth).mean()
    few_tests = (clf.first_tests(2).predict(test.reshape(-1, 30) >> 8) == truth).mean()
    assert one_fern < rate - 0.3 and few_tests < rate  # figure 3.10: more ferns and tests help


def test_add_then_remove_restores_exactly_the_counts(photo: np.ndarray, centres: np.ndarray
                                                     ) -> None:
    clf = FernClassifier(FernConf(num_ferns=25, num_tests=11))
    first = sample_leaves(clf, photo, centres[:25], draw_warps(WARPS, 0), WARPS).reshape(-1, 25)
    clf.add(first, np.tile(np.arange(25), WARPS.num_warps))
    before = _table(clf)
    scores_before = clf.scores(first[:50])
    # New views of old classes and entirely new classes, then their removal.
    more = sample_leaves(clf, photo, centres[15:], draw_warps(WARPS, 1), WARPS).reshape(-1, 25)
    more_labels = np.tile(np.arange(15, 40), WARPS.num_warps)
    clf.add(more, more_labels)
    assert clf.num_classes == 40 and not _same(_table(clf), before)
    clf.remove(more, more_labels)
    assert _same(_table(clf), before)
    np.testing.assert_array_equal(clf.scores(first[:50]), scores_before)


def test_removing_samples_never_added_fails() -> None:
    clf = FernClassifier(FernConf(num_ferns=2, num_tests=3))
    clf.add(np.array([[1, 2]], np.uint16), [7])
    with pytest.raises(ValueError):
        clf.remove(np.array([[1, 2]], np.uint16), [8])     # unknown class
    with pytest.raises(ValueError):
        clf.remove(np.array([[1, 2], [1, 2]], np.uint16), [7, 7])   # more than added
    clf.remove(np.array([[1, 3]], np.uint16), [7])
    with pytest.raises(ValueError):
        _ = clf.nnz  # the (fern 1, leaf 3) count of class 7 went negative
    with pytest.raises(ValueError):
        clf.add(np.array([[8, 0]], np.uint16), [7])        # leaf out of range


def test_large_counts_stay_exact() -> None:
    """Counts are decoded from float32 logs: exact far beyond realistic sample numbers."""
    clf = FernClassifier(FernConf(num_ferns=1, num_tests=2, regularization=1.0))
    n = 300_001
    leaves = np.zeros((n, 1), np.uint16)
    leaves[::3] = 1
    clf.add(leaves, np.zeros(n, np.int64))
    clf.add(np.full((5, 1), 2, np.uint16), np.zeros(5, np.int64))
    clf.remove(np.full((2, 1), 2, np.uint16), np.zeros(2, np.int64))
    _, leaf, _, count = clf.count_table()
    assert dict(zip(leaf.tolist(), count.tolist(), strict=True)) == {0: 200_000, 1: 100_001, 2: 3}


def test_memory_grows_with_samples_not_with_leaves() -> None:
    clf = FernClassifier(FernConf(num_ferns=50, num_tests=14))
    rng = np.random.default_rng(3)
    clf.add(rng.integers(0, 2**14, (1000, 50)).astype(np.uint16), rng.integers(0, 500, 1000))
    assert clf.nnz <= 50 * 1000
    assert clf.nbytes() < clf.dense_nbytes() / 50


def test_arrays_round_trip() -> None:
    rng = np.random.default_rng(4)
    conf = FernConf(num_ferns=8, num_tests=7, seed=5)
    clf = FernClassifier(conf)
    leaves = rng.integers(0, 128, (400, 8)).astype(np.uint16)
    clf.add(leaves, rng.integers(100, 130, 400))
    arrays = clf.to_arrays()
    # stored narrow: 30 classes' columns in one byte, offsets of 400*8 counts in two
    assert (arrays["indices"].dtype, arrays["indptr"].dtype) == (np.uint8, np.uint16)
    back = FernClassifier.from_arrays(conf, arrays)
    assert _same(_table(back), _table(clf))
    np.testing.assert_array_equal(back.scores(leaves[:20]), clf.scores(leaves[:20]))
    with pytest.raises(ValueError):
        FernClassifier.from_arrays(FernConf(num_ferns=8, num_tests=7, seed=6), clf.to_arrays())


def test_subset_and_first_tests_are_consistent_with_training() -> None:
    rng = np.random.default_rng(6)
    clf = FernClassifier(FernConf(num_ferns=4, num_tests=8))
    leaves = rng.integers(0, 256, (500, 4)).astype(np.uint16)
    labels = rng.integers(0, 10, 500)
    clf.add(leaves, labels)
    direct = FernClassifier(FernConf(num_ferns=4, num_tests=3))
    direct.add(leaves >> 5, labels)
    assert _same(_table(clf.first_tests(3)), _table(direct))
    keep = labels < 4
    only = FernClassifier(FernConf(num_ferns=4, num_tests=8))
    only.add(leaves[keep], labels[keep])
    assert _same(_table(clf.subset([0, 1, 2, 3])), _table(only))


def test_compiled_leaves_equal_numpy_leaves(photo: np.ndarray) -> None:
    """The compiled leaves (clamped coordinates) equal numpy's (gathers from a padded copy),
    for patches inside the image, sticking out of it, and centred outside it (clamped)."""
    from reloc_service.algorithms.ferns import kernels

    if kernels.compiled_leaves_at() is None:
        pytest.skip("numba is not installed")
    image = prepare_image(photo, 1.0)
    h, w = image.shape
    rng = np.random.default_rng(7)
    points = np.vstack([rng.uniform(-5, [w + 5, h + 5], (300, 2)),   # also outside: clamped
                        [[0, 0], [w - 1, h - 1], [17, 17], [w - 18, h - 18]]])
    clf = FernClassifier(FernConf(num_ferns=30, num_tests=11, patch_size=32, seed=2))
    pts = np.rint(points).astype(np.int64)
    xs, ys = np.clip(pts[:, 0], 0, w - 1), np.clip(pts[:, 1], 0, h - 1)
    compiled = clf._leaves_at(image, xs, ys, compiled=True)
    np.testing.assert_array_equal(compiled, clf._leaves_at(image, xs, ys, compiled=False))
    np.testing.assert_array_equal(compiled, clf.leaves_at(image, points))
    assert len(np.unique(compiled)) > 100  # real outcomes, not a constant
    # uint8 images (training reads warped uint8 canvases too) give the same leaves.
    np.testing.assert_array_equal(clf._leaves_at(photo, xs, ys, compiled=True),
                                  clf._leaves_at(photo, xs, ys, compiled=False))


def test_skipped_exponentials_cannot_change_a_float32_posterior() -> None:
    """Every class the kernel leaves out of the normaliser (score below the best minus
    ``negligible_log_ratio``) adds, all together, less than half a float32 step to it."""
    from reloc_service.algorithms.ferns.kernels import negligible_log_ratio

    for classes in (2, 150, 2000, 100_000):
        t = negligible_log_ratio(classes)
        left_out = classes * np.exp(-t)  # at most that much of a normaliser >= 1
        assert left_out < np.finfo(np.float32).eps / 2
        assert np.float32(1.0 + left_out) == np.float32(1.0)
