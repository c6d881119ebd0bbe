"""The shared numeric helpers: zero-mean NCC, top-k selection and the BLAS thread limit."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from reloc_service.core.numeric import compile_once, limit_blas_threads, top_k, zncc


def test_zncc_of_related_and_unrelated_images():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(30, 40))
    assert zncc(a, 3 * a + 7) == pytest.approx(1.0)
    assert zncc(a, -a) == pytest.approx(-1.0)
    assert abs(zncc(a, rng.normal(size=(30, 40)))) < 0.1


def test_zncc_of_a_flat_image_is_the_callers_choice():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(30, 40))
    flat = np.full_like(a, 7.0)
    assert zncc(a, flat) == 0.0            # uncorrelated (the none pose finder)
    assert zncc(flat, a, flat=-1.0) == -1.0  # ranked last (ESM picks the best NCC)
    assert zncc(a, a, np.zeros(a.shape, bool), flat=-1.0) == -1.0  # empty mask


def test_zncc_over_a_mask_ignores_the_pixels_outside():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(30, 40))
    b = a.copy()
    mask = np.zeros(a.shape, bool)
    mask[5:25, 5:35] = True
    b[~mask] = rng.normal(size=int((~mask).sum()))
    assert zncc(a, b, mask) == pytest.approx(1.0)
    assert zncc(a, b) < 0.9


def test_top_k_is_best_first_with_ties_to_the_lower_index():
    scores = np.array([0.5, 2.0, 1.0, 2.0, 1.0, -3.0])
    assert top_k(scores, 3).tolist() == [1, 3, 2]
    assert top_k(scores, 10).tolist() == [1, 3, 2, 4, 0, 5]
    assert top_k(scores, 0).tolist() == []
    assert top_k(np.zeros(0), 3).tolist() == []


def test_top_k_keeps_only_the_kept_and_breaks_ties_by_tiebreak():
    scores = np.array([1.0, np.nan, 1.0, 5.0, 1.0, np.inf])
    ids = np.array([30, 10, 20, 40, 5, 60])
    order = top_k(scores, 3, keep=np.isfinite(scores), tiebreak=ids)
    assert order.tolist() == [3, 4, 2]  # 5.0, then the 1.0s by id 5, 20 (30 is the fourth)
    assert top_k(scores, 3, keep=scores > 10).tolist() == [5]
    # A tie across the k-th place goes to the lower id however many tie (never arbitrary).
    tied = np.ones(50)
    ids = np.random.default_rng(3).permutation(50)
    assert sorted(ids[top_k(tied, 5, tiebreak=ids)]) == [0, 1, 2, 3, 4]


@pytest.mark.parametrize("k", [1, 2, 4, 5, 9])
def test_top_k_of_rows_matches_a_stable_sort_and_restores_the_scores(k):
    rng = np.random.default_rng(k)
    scores = rng.integers(-3, 3, (40, 12)).astype(np.float32)  # many ties
    scores[0] = -np.inf
    before = scores.copy()
    got = top_k(scores, k)
    assert np.array_equal(scores, before)
    assert np.array_equal(got, np.argsort(-before, axis=1, kind="stable")[:, :k])


def test_top_k_refuses_what_it_cannot_rank():
    with pytest.raises(ValueError, match=r"expected \(C,\) or \(N, C\)"):
        top_k(np.zeros((2, 2, 2)), 1)
    with pytest.raises(ValueError, match="1-D scores"):
        top_k(np.zeros((2, 3)), 1, keep=np.ones((2, 3), bool))


def test_blas_threads_are_limited_and_restored():
    """Every loaded BLAS (NumPy's at least) takes the limit; 0 leaves them as they are; a
    negative count is refused. The process's counts are put back afterwards."""
    from threadpoolctl import threadpool_info, threadpool_limits

    before = [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
    assert before, "NumPy loads a BLAS"
    with threadpool_limits(limits=None):       # restores the counts on exit
        assert limit_blas_threads(1) == [1] * len(before)
        assert limit_blas_threads(0) == [1] * len(before)
        assert (np.ones((64, 64)) @ np.ones((64, 64)))[0, 0] == 64.0
        with pytest.raises(ValueError, match="expected 0 .* or a positive count, got -2"):
            limit_blas_threads(-2)
    assert [lib["num_threads"] for lib in threadpool_info()
            if lib["user_api"] == "blas"] == before


def test_compile_once_runs_its_factory_once_for_concurrent_first_calls() -> None:
    """Two threads asking at once (as a service's warm-kernels thread and its first query
    do): the factory runs once and both get its result (``functools.cache`` ran it twice)."""
    calls: list[int] = []
    asking = threading.Event()

    def factory() -> object:
        calls.append(1)
        assert asking.wait(30)
        time.sleep(0.2)   # lets the second caller reach the factory, or the lock before it
        return object()

    once = compile_once(factory)
    results: list[object] = []

    def second() -> None:
        asking.set()
        results.append(once())

    threads = [threading.Thread(target=lambda: results.append(once())),
               threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(calls) == 1 and len(results) == 2 and results[0] is results[1]
    assert once() is results[0]


@pytest.mark.parametrize("n,high", [(0, 5), (1, 5), (12, 3), (10_000, 4000), (10_000, 10**12),
                                    (5000, 2**62)])
def test_first_occurrences_are_the_sorted_unique_indices(n, high, monkeypatch):
    """The compiled hash pass and the numpy path both give np.unique's first indices, sorted:
    repeated values, negative ids (-1: no landmark), ids far apart and near 2**63."""
    from reloc_service.core import numeric

    rng = np.random.default_rng(n + high % 1000)
    values = rng.integers(-3 if high < 100 else 0, high, n)
    values[::7] = -1
    expected = np.sort(np.unique(values, return_index=True)[1])
    got = numeric.first_occurrences(values)
    assert got.dtype == np.int64 and np.array_equal(got, expected)
    monkeypatch.setattr(numeric, "_first_occurrence_kernel", lambda: None)
    assert np.array_equal(numeric.first_occurrences(values), expected)
