"""Formatting of ``reloc bench --only accuracy``: each cell (recalls, off and wrong rates,
cov scale, p50), the Markdown table, its per-dataset details and notes. The section itself is
measured by :mod:`.accuracy`."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from .accuracy import NOT_APPLICABLE, TABLE_RECALLS
from .limit import LIMIT_ORB_FEATURES


def _pct(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{100 * value:.0f}%"


def _ms(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.0f} ms" if value >= 10 else f"{value:.1f} ms"


def _ratio(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.1f}x"


def _scale(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.1f}"


def cell(r: Mapping[str, Any]) -> str:
    """``recall@5cm/5deg / recall@25cm/10deg / off% / wrong% / cov scale / p50 ms`` of one
    column."""
    if "error" in r:
        return "n/a" if str(r["error"]).startswith(NOT_APPLICABLE) else "error"
    rec = r["recall"]
    return " / ".join([*(_pct(rec.get(k)) for k in TABLE_RECALLS), _pct(r.get("off_rate")),
                       _pct(r["wrong_rate"]), _scale(r.get("covariance_scale")),
                       _ms(r["p50_ms"])])


def column_label(section: Mapping[str, Any], column: str) -> str:
    if column in section["peers"]:
        return section["peers"][column]
    return f"`{column}`" + (" (default)" if column == section["default_method"] else "")


def table_lines(section: Mapping[str, Any]) -> list[str]:
    """The Markdown table: one row per dataset, one column per method and peer."""
    columns = section["columns"]
    header = ["dataset", "keyframes / queries", *[column_label(section, c) for c in columns]]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for name, d in section["datasets"].items():
        if "error" in d:
            row = [name, "-", *(["failed"] * len(columns))]
        else:
            row = [name, f"{d['keyframes']} / {d['queries']}",
                   *[cell(d["results"][c]) if c in d["results"] else "not run"
                     for c in columns]]
        lines.append("| " + " | ".join(row) + " |")
    return lines


def recall_gap_points(d: Mapping[str, Any], method: str, reference: str = "sbi+p3p",
                      key: str = "5cm_5deg") -> float | None:
    """``method``'s recall minus ``reference``'s on one dataset record, in percentage points
    (None when either is missing or failed)."""
    a, b = d.get("results", {}).get(method), d.get("results", {}).get(reference)
    if not a or not b or "error" in a or "error" in b:
        return None
    return 100.0 * (a["recall"][key] - b["recall"][key])


def detail_lines(section: Mapping[str, Any]) -> list[str]:
    """One row per dataset and column: recalls, wrong and not-relocalized rates, p50 and
    p99, the default's recall gap to ``sbi+p3p`` and the share its first step answered."""
    header = ["dataset", "method", "recall 5cm/5deg", "recall 25cm/10deg", "off", "wrong",
              "cov scale", "cov rms", "beyond 3 sigma", "not relocalized", "p50 ms", "p90 ms",
              "p99 ms", "recall - `sbi+p3p`", "first step", "decode + ORB p50", "p50 / limit"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for name, d in section["datasets"].items():
        if "error" in d:
            lines.append("| " + " | ".join([name, "failed", *["-"] * (len(header) - 2)]) + " |")
            continue
        for c in section["columns"]:
            r = d["results"].get(c)
            if r is None or "error" in r:
                continue
            gap = recall_gap_points(d, c) if c == section["default_method"] else None
            first = r.get("first_step") or {}
            share = first.get("share_of_returned")
            lines.append("| " + " | ".join([
                f"{name} ({d['keyframes']} / {d['queries']})", column_label(section, c),
                _pct(r["recall"].get("5cm_5deg")), _pct(r["recall"].get("25cm_10deg")),
                _pct(r.get("off_rate")), _pct(r["wrong_rate"]),
                _scale(r.get("covariance_scale")), _scale(r.get("covariance_rms_scale")),
                _pct(r.get("beyond_3_sigma")), _pct(r.get("not_relocalized_rate")),
                _ms(r["p50_ms"]), _ms(r.get("p90_ms")),
                _ms(r["p99_ms"]), "-" if gap is None else f"{gap:+.0f} points",
                "-" if share is None else f"{_pct(share)} by `{first['step']}`",
                _ms(d.get("limit", {}).get("orb_limit_p50_ms")), _ratio(r.get("over_limit"))])
                + " |")
    return lines


def note_lines(section: Mapping[str, Any]) -> list[str]:
    """Skipped sets, failed datasets and columns that did not apply or failed."""
    notes = [f"- {n}" for n in section.get("notes", [])]
    for name, d in section["datasets"].items():
        if "error" in d:
            notes.append(f"- {name}: **failed**: `{d['error']}`")
            continue
        for c, r in d["results"].items():
            if "error" in r:
                notes.append(f"- {name}, {column_label(section, c)}: `{r['error']}`")
    return notes


def markdown_lines(section: Mapping[str, Any]) -> list[str]:
    """The section of ``docs/performance.md``."""
    return (["## Accuracy on datasets", "",
             "Each cell: recall at 5 cm / 5 deg / recall at 25 cm / 10 deg / off (returned "
             "but beyond 25 cm or 10 deg) / wrong (returned but beyond 50 cm or 15 deg) / cov "
             "scale (1 when the stated covariance fits the errors) / p50 latency, all as "
             "`reloc eval` computes them (rates over all queries; latency from the decoded "
             "image to the answer, OpenCV on one thread). "
             f"How: {section['how']}. The default method is the service "
             "config's `service.default_method`. Plain OpenCV: SIFT, `BFMatcher` knn ratio "
             "0.8 against the landmarks of every keyframe, `cv2.solvePnPRansac`, accepted at "
             ">= 20 inliers; dedup keeps one descriptor per landmark. \"first step\": the "
             "share of a fallback chain's answers its first step gave. \"decode + ORB\": "
             f"reading and decoding each query image and extracting {LIMIT_ORB_FEATURES} ORB "
             "features, timed on the same queries in the same run; \"p50 / limit\": each "
             "column's p50 over that limit's p50.", ""]
            + detail_lines(section) + [""] + (note_lines(section) + [""]
                                              if note_lines(section) else []))
