"""Human-readable tables of an :class:`~reloc_service.tools.eval.results.EvalResult` (one row per
method), for the terminal and for Markdown notes."""

from __future__ import annotations

import math
import re
from typing import TYPE_CHECKING, Any

import numpy as np

from .metrics import OFF_THRESHOLD, RECALL_THRESHOLDS, WRONG_THRESHOLD, threshold_key

if TYPE_CHECKING:
    from .results import EvalResult, MethodResult, MethodSummary

_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")

_COLUMNS = (["method"]
            + [f"@{t * 100:g}cm/{r:g}deg" for t, r in RECALL_THRESHOLDS]
            + ["med t cm", "med r deg", "t err/sigma", "cov scale", "cov range", "cov rms",
               ">3 sigma %", "off %",
               "wrong %", "not reloc %", "p50 ms", "p99 ms"])


def _pct(x: float) -> str:
    return "-" if math.isnan(x) else f"{100 * x:.1f}"


def _num(x: float, scale: float = 1.0, digits: int = 1) -> str:
    return "-" if x is None or math.isnan(x) else f"{x * scale:.{digits}f}"


def _range(s: MethodSummary) -> str:
    """``low-high`` of the cov scale's confidence interval, its coverage when under 95 %."""
    if math.isnan(s.covariance_scale_low):
        return "-"
    text = f"{s.covariance_scale_low:.2f}-{_num(s.covariance_scale_high, 1, 2)}"
    return text if s.covariance_scale_coverage >= 0.95 else \
        f"{text} ({100 * s.covariance_scale_coverage:.0f}%)"


def table_rows(result: EvalResult) -> list[list[str]]:
    """One row of strings per method, in :data:`_COLUMNS` order (recalls in percent)."""
    rows = []
    for m in result.methods:
        s = m.summary
        rows.append([m.method]
                    + [_pct(s.recall[threshold_key(t, r)]) for t, r in RECALL_THRESHOLDS]
                    + [_num(s.median_t_err_m, 100, 2), _num(s.median_r_err_deg, 1, 2),
                       _num(s.median_t_err_over_sigma, 1, 1), _num(s.covariance_scale, 1, 2),
                       _range(s), _num(s.covariance_rms_scale, 1, 2), _pct(s.beyond_3_sigma),
                       _pct(s.off_rate), _pct(s.wrong_rate),
                       _pct(s.not_relocalized_rate), _num(s.latency_p50_ms),
                       _num(s.latency_p99_ms)])
    return rows


def format_table(result: EvalResult) -> str:
    """Aligned plain-text table, one row per method; recall columns are percentages."""
    rows = [list(_COLUMNS)] + table_rows(result)
    widths = [max(len(r[i]) for r in rows) for i in range(len(_COLUMNS))]
    lines = []
    for n, row in enumerate(rows):
        cells = [row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:],
                                                                         strict=True)]
        lines.append("  ".join(cells).rstrip())
        if n == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_markdown(result: EvalResult) -> str:
    """The same table in GitHub Markdown."""
    rows = table_rows(result)
    head = "| " + " | ".join(_COLUMNS) + " |"
    rule = "|" + "|".join(["---"] + ["---:"] * (len(_COLUMNS) - 1)) + "|"
    return "\n".join([head, rule] + ["| " + " | ".join(r) + " |" for r in rows])


def _measured_sigma(measured: dict[str, Any] | None) -> str:
    """The map's measured keyframe pose sigma, as the header states it ("" when none)."""
    if measured is None:
        return ""
    return (f"; keyframe pose sigma measured {100 * measured['position_m']:.2f} cm, "
            f"{measured['rotation_deg']:.3f} deg (on {measured['keyframes']} keyframes)")


def format_header(result: EvalResult) -> str:
    """Dataset, map and timing lines printed above the table."""
    d, mp = result.dataset, result.map
    lm_err = ("" if mp.median_landmark_error_m is None
              else f", median landmark error {100 * mp.median_landmark_error_m:.2f} cm")
    if mp.median_landmark_error_m is not None and mp.p90_landmark_error_m is not None:
        lm_err += f" (90th percentile {100 * mp.p90_landmark_error_m:.2f} cm)"
    if mp.landmarks_per_keyframe:
        per_kf = np.asarray(mp.landmarks_per_keyframe)
        lm_err = (f", per keyframe median {np.median(per_kf):.0f} min {per_kf.min()} max "
                  f"{per_kf.max()}{lm_err}")
    return "\n".join([
        f"dataset {d['name']} ({d['root']}): {d['map_frames']} map frames, "
        f"{d['query_frames']} queries; backend {result.backend}",
        f"map: {mp.keyframes} keyframes, {mp.landmarks} landmarks ({mp.landmark_source}"
        f"{lm_err}); built in {mp.build_time_s:.2f} s, trained in {mp.train_time_s:.2f} s"
        f"{_measured_sigma(mp.keyframe_pose_sigma)}",
        f"recall: queries with a pose within the thresholds; off / wrong: pose returned but "
        f"beyond {OFF_THRESHOLD[0] * 100:g} cm / {OFF_THRESHOLD[1]:g} deg / "
        f"{WRONG_THRESHOLD[0] * 100:g} cm / {WRONG_THRESHOLD[1]:g} deg (% of all queries); "
        f"cov scale: 1 when the stated covariance fits the errors, 2 when it is twice too "
        f"confident; cov range: its 95 % confidence interval from the order statistics of "
        f"the median (the probability it holds, when fewer answers cannot reach 95 %)"])


def format_report(result: EvalResult) -> str:
    """Header and table, as ``reloc eval`` prints them."""
    return format_header(result) + "\n\n" + format_table(result)


def format_failures(method: MethodResult, limit: int = 5) -> str:
    """The most common reasons a method gave no pose, ``count  reason`` lines. Reasons that
    differ only in their numbers are counted together, shown by their first example
    (``e.g. ...``)."""
    groups: dict[str, list[str]] = {}
    for q in method.queries:
        if not q.returned:
            reason = q.reason or "(no reason)"
            groups.setdefault(_NUMBER.sub("#", reason), []).append(reason)
    top = sorted(groups.values(), key=lambda g: (-len(g), g[0]))[:limit]
    return "\n".join(f"{len(g):4d}  {'e.g. ' if len(set(g)) > 1 else ''}{g[0]}" for g in top)
