"""The few distribution functions the answer path reads (chi-square, normal, binomial,
noncentral chi-square, F and noncentral F quantiles and tails), with the ``scipy.stats`` names and answers
but through ``scipy.special``: importing ``scipy.stats`` takes 2-3 s of a service's start-up.

Each function calls the very ``scipy.special`` ufunc ``scipy.stats`` calls for it (scipy's
``_continuous_distns``/``_discrete_distns``) and handles the support's bounds the way
``rv_continuous``/``rv_discrete`` do, so the results are the same floats (checked against
``scipy.stats`` in ``tests/test_distributions.py``). Scalars in, floats out: the callers ask
for one threshold or one tail at a time. Used as ``from ..core import distributions as
stats``, a drop-in for the calls below.
"""

from __future__ import annotations

import math

from scipy import special
from scipy.special import _ufuncs as _scu  # the Boost binomial and ncf scipy.stats calls


def _nan_unless(valid: bool) -> float | None:
    return None if valid else math.nan


class _Chi2:
    """Chi-square with ``df`` degrees of freedom (``scipy.stats.chi2``)."""

    @staticmethod
    def ppf(q: float, df: float) -> float:
        if (bad := _nan_unless(df > 0 and 0.0 <= q <= 1.0)) is not None:
            return bad
        return float(2.0 * special.gammaincinv(df / 2.0, q))

    @staticmethod
    def isf(p: float, df: float) -> float:
        if (bad := _nan_unless(df > 0 and 0.0 <= p <= 1.0)) is not None:
            return bad
        if p == 0.0:
            return math.inf
        if p == 1.0:
            return 0.0
        return float(special.chdtri(df, p))

    @classmethod
    def median(cls, df: float) -> float:
        return cls.ppf(0.5, df)


class _Norm:
    """The standard normal (``scipy.stats.norm``)."""

    @staticmethod
    def sf(x: float) -> float:
        return float(special.ndtr(-x))

    @staticmethod
    def cdf(x: float) -> float:
        return float(special.ndtr(x))


class _Binom:
    """The binomial of ``n`` draws with probability ``p`` (``scipy.stats.binom``); its
    support is 0..n."""

    @staticmethod
    def _valid(n: float, p: float) -> bool:
        return n >= 0 and float(n).is_integer() and 0.0 <= p <= 1.0

    @classmethod
    def sf(cls, k: float, n: float, p: float) -> float:
        if (bad := _nan_unless(cls._valid(n, p) and not math.isnan(k))) is not None:
            return bad
        if k < 0:
            return 1.0
        if k >= n:
            return 0.0
        return float(_scu._binom_sf(math.floor(k), n, p))

    @classmethod
    def ppf(cls, q: float, n: float, p: float) -> float:
        if (bad := _nan_unless(cls._valid(n, p) and 0.0 <= q <= 1.0)) is not None:
            return bad
        if q == 0.0:
            return -1.0
        if q == 1.0:
            return float(n)
        return float(_scu._binom_ppf(q, n, p))


class _Ncx2:
    """The noncentral chi-square (``scipy.stats.ncx2``)."""

    @staticmethod
    def cdf(x: float, df: float, nc: float) -> float:
        if (bad := _nan_unless(df > 0 and math.isfinite(df) and nc >= 0)) is not None:
            return bad
        if x <= 0.0:
            return 0.0
        if x == math.inf:
            return 1.0
        return float(special.chndtr(x, df, nc) if nc != 0 else special.chdtr(df, x))


class _F:
    """Fisher's F with ``dfn`` and ``dfd`` degrees of freedom (``scipy.stats.f``)."""

    @staticmethod
    def sf(x: float, dfn: float, dfd: float) -> float:
        if (bad := _nan_unless(dfn > 0 and dfd > 0)) is not None:
            return bad
        if x <= 0.0:
            return 1.0
        if x == math.inf:
            return 0.0
        return float(special.fdtrc(dfn, dfd, x))


class _Ncf:
    """The noncentral F with ``dfn`` and ``dfd`` degrees of freedom and noncentrality ``nc``
    (``scipy.stats.ncf``: Boost's, which stays finite where ``special.ncfdtr`` returns NaN
    for noncentralities of a few thousand)."""

    @staticmethod
    def sf(x: float, dfn: float, dfd: float, nc: float) -> float:
        if (bad := _nan_unless(dfn > 0 and dfd > 0 and nc >= 0)) is not None:
            return bad
        if x <= 0.0:
            return 1.0
        if x == math.inf:
            return 0.0
        return float(_scu._ncf_sf(x, dfn, dfd, nc))


chi2 = _Chi2()
norm = _Norm()
binom = _Binom()
ncx2 = _Ncx2()
f = _F()
ncf = _Ncf()
