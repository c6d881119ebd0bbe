"""The distribution functions of core/distributions.py give scipy.stats' floats, bounds and
invalid arguments included, and the service's modules import no scipy.stats."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from reloc_service.core import distributions as dist

PROBABILITIES = [0.0, 1e-12, 1e-6, 0.01, 0.05, 0.5, 0.9, 0.99, 0.999, 1 - 1e-9, 1.0, -0.1, 1.5]


def _same(ours: float, theirs: float) -> bool:
    theirs = float(theirs)
    return (math.isnan(ours) and math.isnan(theirs)) or ours == theirs


@pytest.mark.parametrize("df", [1, 2, 3, 6, 0.5, 17.5, 0, -1])
def test_chi2_quantiles_are_scipy_stats(df: float) -> None:
    for q in PROBABILITIES:
        assert _same(dist.chi2.ppf(q, df), stats.chi2.ppf(q, df)), (q, df)
        assert _same(dist.chi2.isf(q, df), stats.chi2.isf(q, df)), (q, df)
    assert _same(dist.chi2.median(df), stats.chi2.median(df))


def test_normal_tails_are_scipy_stats() -> None:
    for x in [-np.inf, -40.0, -3.0, -0.5, 0.0, 1e-9, 3.0, 8.5, 40.0, np.inf, np.nan]:
        assert _same(dist.norm.sf(x), stats.norm.sf(x)), x
        assert _same(dist.norm.cdf(x), stats.norm.cdf(x)), x


@pytest.mark.parametrize("n", [0, 1, 2, 7, 40, 301, 5000])
@pytest.mark.parametrize("p", [0.0, 0.0027, 0.5, 0.93, 1.0])
def test_binomial_tails_and_quantiles_are_scipy_stats(n: int, p: float) -> None:
    for k in [-5, -1, 0, 1, 2, n // 3, n // 2, n - 1, n, n + 3, 2.5, np.nan]:
        assert _same(dist.binom.sf(k, n, p), stats.binom.sf(k, n, p)), (k, n, p)
    for q in PROBABILITIES:
        assert _same(dist.binom.ppf(q, n, p), stats.binom.ppf(q, n, p)), (q, n, p)


def test_binomial_refuses_what_scipy_stats_refuses() -> None:
    for n, p in [(2.5, 0.5), (-1, 0.5), (10, 1.5), (10, -0.1)]:
        assert math.isnan(dist.binom.sf(1, n, p)) and math.isnan(stats.binom.sf(1, n, p))
        assert math.isnan(dist.binom.ppf(0.5, n, p))


@pytest.mark.parametrize("df", [1, 2, 4, 6.5, 0, -2])
@pytest.mark.parametrize("nc", [0.0, 1e-3, 2.0, 30.0, -1.0])
def test_noncentral_chi2_cdf_is_scipy_stats(df: float, nc: float) -> None:
    for x in [-1.0, 0.0, 1e-6, 0.5, 3.0, 12.0, 80.0, np.inf]:
        assert _same(dist.ncx2.cdf(x, df, nc), stats.ncx2.cdf(x, df, nc)), (x, df, nc)


@pytest.mark.parametrize("dfn, dfd", [(2, 1), (2, 7), (2, 300), (3, 11.5), (0, 4), (2, -1)])
def test_f_tail_is_scipy_stats(dfn: float, dfd: float) -> None:
    for x in [-1.0, 0.0, 1e-8, 0.3, 1.0, 4.7, 60.0, np.inf]:
        assert _same(dist.f.sf(x, dfn, dfd), stats.f.sf(x, dfn, dfd)), (x, dfn, dfd)


@pytest.mark.parametrize("dfd", [1, 7, 50, 300, 6400])
@pytest.mark.parametrize("nc", [0.0, 2.0, 30.0, 1570.2901247293776, 2967.3, 1e6, -1.0])
def test_noncentral_f_tail_is_scipy_stats(dfd: float, nc: float) -> None:
    for x in [-1.0, 0.0, 1e-8, 0.3, 4.7, 60.0, np.inf]:
        assert _same(dist.ncf.sf(x, 2, dfd, nc), stats.ncf.sf(x, 2, dfd, nc)), (x, dfd, nc)


def test_noncentral_f_tail_is_finite_where_ncfdtr_is_not() -> None:
    """``special.ncfdtr`` returns NaN at some noncentralities of a few thousand (a test's
    power at an error its data exclude by far); the tail the power reads stays a number."""
    from scipy import special

    limit = float(special.fdtri(2, 50, 0.99))   # ncfdtr gives NaN here (scipy 1.17)
    assert dist.ncf.sf(limit, 2, 50, 1570.2901247293776) == pytest.approx(1.0)


@pytest.mark.slow   # a fresh interpreter: its imports take seconds
def test_serving_imports_no_scipy_stats() -> None:
    """What ``reloc serve`` imports to answer (the service, the default method's modules)
    leaves scipy.stats unloaded: its import alone took 2-3 s of the start-up."""
    code = ("import sys, reloc_service.service.app, reloc_service.service.processes, "
            "reloc_service.algorithms.relocalizers.factory, "
            "reloc_service.algorithms.relocalizers.tracking_fallback, "
            "reloc_service.service.ros2.map_frame; "
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.strip() == "False"
