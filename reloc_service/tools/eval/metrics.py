"""Pure evaluation metrics: recall at error thresholds, wrong-pose rate, percentiles, and the rank
of the chosen keyframe among the ground-truth-closest ones (thesis figure 3.2).

Conventions: per-query arrays have one entry per query; a query that returned no pose has
``returned`` False and NaN errors. Rates are fractions of *all* queries, in [0, 1].
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

#: (translation metres, rotation degrees) thresholds of the recall columns.
RECALL_THRESHOLDS: tuple[tuple[float, float], ...] = ((0.05, 5.0), (0.25, 10.0), (0.50, 15.0))
#: A returned pose worse than this (translation metres, rotation degrees) is *wrong*.
WRONG_THRESHOLD: tuple[float, float] = (0.50, 15.0)
#: A returned pose worse than this is *off*: no longer usable to re-anchor odometry, though
#: not yet wrong. The rate of off poses is the second headline figure next to the wrong rate.
OFF_THRESHOLD: tuple[float, float] = (0.25, 10.0)


def threshold_key(t_max_m: float, r_max_deg: float) -> str:
    """Stable name of a threshold pair in reports and JSON, e.g. ``"5cm_5deg"``."""
    return f"{t_max_m * 100:g}cm_{r_max_deg:g}deg"


def _per_query(returned: npt.ArrayLike, **values: npt.ArrayLike
               ) -> tuple[list[Array], npt.NDArray[np.bool_]]:
    """``values`` as flat float64 arrays and ``returned`` as a flat mask, all one entry per
    query (ValueError naming each length otherwise)."""
    arrays = [np.asarray(v, dtype=np.float64).ravel() for v in values.values()]
    ok = np.asarray(returned, dtype=bool).ravel()
    if any(len(a) != len(ok) for a in arrays):
        lengths = ", ".join(f"{name} {len(a)}" for name, a in zip(values, arrays, strict=True))
        raise ValueError(f"per-query arrays differ in length: {lengths}, returned {len(ok)}")
    return arrays, ok


def _arrays(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike
            ) -> tuple[Array, Array, npt.NDArray[np.bool_]]:
    (t, r), ok = _per_query(returned, t=t_err_m, r=r_err_deg)
    if np.any(ok & ~(np.isfinite(t) & np.isfinite(r))):
        raise ValueError("a returned pose has a non-finite error; expected finite errors for "
                         "every returned pose")
    return t, r, ok


def within(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike,
           t_max_m: float, r_max_deg: float) -> npt.NDArray[np.bool_]:
    """(Q,) mask of queries that returned a pose within both thresholds (inclusive)."""
    t, r, ok = _arrays(t_err_m, r_err_deg, returned)
    with np.errstate(invalid="ignore"):
        return ok & (t <= t_max_m) & (r <= r_max_deg)


def recall(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike,
           t_max_m: float, r_max_deg: float) -> float:
    """Fraction of all queries with a returned pose within ``t_max_m`` and ``r_max_deg``;
    NaN when there is no query."""
    mask = within(t_err_m, r_err_deg, returned, t_max_m, r_max_deg)
    return float(mask.mean()) if len(mask) else math.nan


def error_over_sigma(t_err_m: npt.ArrayLike, sigma_m: npt.ArrayLike, returned: npt.ArrayLike
                     ) -> float:
    """Median of ``t_err_m / sigma_m`` over returned poses with a finite, positive stated
    sigma (the largest axis of the position covariance): how far the answers are from the
    truth in units of the precision they claim. A covariance that says what it knows gives
    about 1 (0.7 to 1.5 for a Gaussian, from one dominant axis to three equal ones); 10 means
    the answers are ten times less precise than stated. NaN when no pose qualifies."""
    (t, s), ok = _per_query(returned, t=t_err_m, sigma=sigma_m)
    with np.errstate(invalid="ignore"):
        use = ok & np.isfinite(t) & np.isfinite(s) & (s > 0)
    return float(np.median(t[use] / s[use])) if use.any() else math.nan


#: Median of the chi distribution with 3 degrees of freedom: the median Mahalanobis length of
#: a 3-D Gaussian error under its own covariance (``sqrt(scipy.stats.chi2.ppf(0.5, 3))``).
CHI3_MEDIAN = 1.5381722544550522


def translation_mahalanobis(est_world_from_cam: npt.ArrayLike, gt_world_from_cam: npt.ArrayLike,
                            covariance: npt.ArrayLike,
                            truth_covariance: npt.ArrayLike | None = None) -> float:
    """Length of the translation error under the pose's stated covariance (6x6, twist
    (rho, omega), right perturbation ``world_from_cam @ exp(xi)``): the error is taken into
    the estimate's camera frame (``rho ~ R^T (t_gt - t_est)``) and weighed by the inverse of
    the translation block. ``truth_covariance`` (6x6, the same convention for the ground
    truth pose) is how far the ground truth itself may be from the true pose: independent of
    the estimate's error, its translation block (a right perturbation of the ground truth
    moves its centre by ``R_gt rho``, seen from the estimate as ``R_est^T R_gt rho``) adds to
    the estimate's. inf when the block is singular or not finite."""
    est, gt = np.asarray(est_world_from_cam, np.float64), np.asarray(gt_world_from_cam, np.float64)
    block = np.asarray(covariance, np.float64)[:3, :3]
    if truth_covariance is not None:
        turn = est[:3, :3].T @ gt[:3, :3]
        block = block + turn @ np.asarray(truth_covariance, np.float64)[:3, :3] @ turn.T
    rho = est[:3, :3].T @ (gt[:3, 3] - est[:3, 3])
    if not np.all(np.isfinite(block)):
        return math.inf
    try:
        weighed = np.linalg.solve(block, rho)
    except np.linalg.LinAlgError:
        return math.inf
    return math.sqrt(max(float(rho @ weighed), 0.0))


def covariance_scale(mahalanobis: npt.ArrayLike, returned: npt.ArrayLike) -> float:
    """How many times larger the stated position sigmas would have to be for the errors to
    look like draws from them: the median Mahalanobis length of the returned poses' errors
    (:func:`translation_mahalanobis`) over :data:`CHI3_MEDIAN`, its median for Gaussian
    errors that follow the stated covariance. 1: honest; 2: the sigmas are half what the
    errors show (a filter fusing the poses should inflate them twofold); NaN when no
    returned pose has a finite value."""
    (d,), ok = _per_query(returned, d=mahalanobis)
    with np.errstate(invalid="ignore"):
        use = ok & np.isfinite(d)
    return float(np.median(d[use]) / CHI3_MEDIAN) if use.any() else math.nan


#: Share of 3-D Gaussian errors beyond 3 sigmas of their own covariance (Mahalanobis length
#: over 3: ``scipy.stats.chi2.sf(9, 3)``): what :func:`beyond_sigma_share` gives for honest
#: Gaussian answers.
CHI3_BEYOND_3 = 0.02929088653488826


def beyond_sigma_share(mahalanobis: npt.ArrayLike, returned: npt.ArrayLike,
                       limit: float = 3.0) -> float:
    """Share of the returned poses with a covariance whose Mahalanobis length
    (:func:`translation_mahalanobis`) exceeds ``limit``: the tail the median behind
    :func:`covariance_scale` does not see (:data:`CHI3_BEYOND_3` for honest Gaussian errors at
    3). NaN when no returned pose has a length; an infinite length (a singular block) counts
    as beyond."""
    (d,), ok = _per_query(returned, d=mahalanobis)
    d = d[ok & ~np.isnan(d)]
    return float(np.mean(d > limit)) if len(d) else math.nan


def covariance_rms_scale(mahalanobis: npt.ArrayLike, returned: npt.ArrayLike) -> float:
    """How many times larger the stated position sigmas would have to be for the errors'
    second moment to match them: ``sqrt(mean(d^2) / 3)`` over the returned poses' Mahalanobis
    lengths ``d`` (3 is the mean of chi-square with 3 degrees of freedom). A Kalman filter
    fusing the answers weighs them by their covariance as a second moment, so this is the
    scale it needs; it exceeds :func:`covariance_scale` where the errors have heavier tails
    than a Gaussian (a few answers far out, the median honest). NaN when no returned pose has
    a length; infinite when one is."""
    (d,), ok = _per_query(returned, d=mahalanobis)
    d = d[ok & ~np.isnan(d)]
    return float(np.sqrt(np.mean(d**2) / 3.0)) if len(d) else math.nan


def covariance_scale_interval(mahalanobis: npt.ArrayLike, returned: npt.ArrayLike,
                              level: float = 0.95) -> tuple[float, float, float]:
    """(low, high, coverage): a distribution-free confidence interval of
    :func:`covariance_scale` from the order statistics of the median. With n answers, the
    j-th smallest and the j-th largest Mahalanobis lengths bracket the true median with
    probability 1 - 2 P(Binomial(n, 1/2) < j), whatever their distribution; j is the largest
    that keeps this at least ``level``. With too few answers for ``level`` (n <= 5 at 95 %),
    the interval is the smallest and largest length and ``coverage`` says what it reaches:
    a set of 5 answers cannot tell a scale of 0.58 from 1. NaNs when fewer than two answers
    have a length, or none a finite one (an infinite one counts: it bounds the interval
    above): one length would be an interval of zero width that holds the median with
    probability 0."""
    (d,), ok = _per_query(returned, d=mahalanobis)
    with np.errstate(invalid="ignore"):
        d = np.sort(d[ok & ~np.isnan(d)])
    n = len(d)
    if n < 2 or not np.isfinite(d[0]):
        return math.nan, math.nan, math.nan
    # P(Binomial(n, 1/2) < j) for j = 0..n, exact in integers.
    below = np.cumsum([math.comb(n, i) for i in range(n + 1)]) / 2.0**n
    tail = np.concatenate([[0.0], below[:-1]])
    fits = np.flatnonzero(1.0 - 2.0 * tail[: n // 2 + 1] >= level)
    j = max(int(fits[-1]), 1) if len(fits) else 1   # 1-based order statistic
    coverage = 1.0 - 2.0 * float(tail[j])
    return float(d[j - 1] / CHI3_MEDIAN), float(d[n - j] / CHI3_MEDIAN), coverage


def recalls(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike,
            thresholds: tuple[tuple[float, float], ...] = RECALL_THRESHOLDS) -> dict[str, float]:
    """``{threshold_key: recall}`` for each (metres, degrees) pair of ``thresholds``."""
    return {threshold_key(t, r): recall(t_err_m, r_err_deg, returned, t, r)
            for t, r in thresholds}


def wrong_mask(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike,
               t_max_m: float = WRONG_THRESHOLD[0], r_max_deg: float = WRONG_THRESHOLD[1]
               ) -> npt.NDArray[np.bool_]:
    """(Q,) mask of *wrong* poses: returned, but beyond ``t_max_m`` or ``r_max_deg``."""
    t, r, ok = _arrays(t_err_m, r_err_deg, returned)
    with np.errstate(invalid="ignore"):
        return ok & ((t > t_max_m) | (r > r_max_deg))


def wrong_rate(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike,
               t_max_m: float = WRONG_THRESHOLD[0], r_max_deg: float = WRONG_THRESHOLD[1]
               ) -> float:
    """Fraction of all queries with a wrong pose (see :func:`wrong_mask`); NaN if no query."""
    mask = wrong_mask(t_err_m, r_err_deg, returned, t_max_m, r_max_deg)
    return float(mask.mean()) if len(mask) else math.nan


def off_rate(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike
             ) -> float:
    """Fraction of all queries with a returned pose beyond :data:`OFF_THRESHOLD`; NaN if no
    query."""
    return wrong_rate(t_err_m, r_err_deg, returned, *OFF_THRESHOLD)


def not_relocalized_rate(returned: npt.ArrayLike) -> float:
    """Fraction of all queries that returned no pose; NaN if no query."""
    ok = np.asarray(returned, dtype=bool).ravel()
    return float((~ok).mean()) if len(ok) else math.nan


def percentile(values: npt.ArrayLike, q: float) -> float:
    """The ``q``-th percentile (0..100, linear interpolation) of the finite ``values``; NaN
    when there is none."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    return float(np.percentile(v, q)) if len(v) else math.nan


def median_errors(t_err_m: npt.ArrayLike, r_err_deg: npt.ArrayLike, returned: npt.ArrayLike
                  ) -> tuple[float, float]:
    """Median translation (m) and rotation (deg) errors over returned poses; NaN if none."""
    t, r, ok = _arrays(t_err_m, r_err_deg, returned)
    return percentile(t[ok], 50.0), percentile(r[ok], 50.0)


def closest_ranks(query_positions_world: npt.ArrayLike, keyframe_positions_world: npt.ArrayLike,
                  chosen_index: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Rank k (1 = closest) of each query's chosen keyframe among all keyframes ordered by the
    distance of their camera centre to the query's ground-truth centre (thesis figure 3.2).

    Args:
        query_positions_world: (Q, 3) ground-truth query camera centres.
        keyframe_positions_world: (K, 3) keyframe camera centres.
        chosen_index: (Q,) row of the chosen keyframe in ``keyframe_positions_world``, -1 for
            none.

    Returns:
        (Q,) int64 ranks; a tie counts in the chosen keyframe's favour (rank = 1 + the number
        of keyframes strictly closer); 0 where ``chosen_index`` is -1.
    """
    q = np.asarray(query_positions_world, dtype=np.float64).reshape(-1, 3)
    kf = np.asarray(keyframe_positions_world, dtype=np.float64).reshape(-1, 3)
    chosen = np.asarray(chosen_index, dtype=np.int64).ravel()
    if len(chosen) != len(q):
        raise ValueError(f"chosen_index: expected {len(q)} entries (one per query), got "
                         f"{len(chosen)}")
    if np.any((chosen < -1) | (chosen >= len(kf))):
        raise ValueError(f"chosen_index: expected -1 or a row in [0, {len(kf)}), got "
                         f"{chosen[(chosen < -1) | (chosen >= len(kf))][:5].tolist()}")
    dist = np.linalg.norm(q[:, None, :] - kf[None, :, :], axis=2)  # (Q, K)
    has = chosen >= 0
    chosen_dist = dist[np.arange(len(q)), np.where(has, chosen, 0)] if len(kf) else np.zeros(len(q))
    ranks = 1 + np.sum(dist < chosen_dist[:, None], axis=1)
    return np.where(has, ranks, 0).astype(np.int64)


def rank_histogram(ranks: npt.ArrayLike) -> dict[int, int]:
    """``{k: count}`` over the positive ``ranks`` (0 = no keyframe chosen is left out), sorted."""
    r = np.asarray(ranks, dtype=np.int64).ravel()
    values, counts = np.unique(r[r > 0], return_counts=True)
    return {int(v): int(c) for v, c in zip(values, counts, strict=True)}
