"""Reporting of ``reloc bench --only soak``: the run's summaries (queries, restarts, resident
memory), its Markdown table and the resident-memory plot. The run itself is in
:mod:`.soak`."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .samples import pct_ms

if TYPE_CHECKING:
    from .soak_ledger import Outcomes

#: How the service is stopped, in turn: ``kill -9`` and SIGTERM.
STOP_KINDS = ("kill9", "sigterm")


def query_summary(out: Outcomes) -> dict[str, Any]:
    answered = out.counts["ok"] + out.counts["not_relocalized"]
    errors = {k: v for k, v in sorted(out.counts.items()) if k not in ("ok", "not_relocalized")}
    return {"sent": out.sent, "answered": answered, "ok": out.counts["ok"],
            "not_relocalized": out.counts["not_relocalized"], "errors_by_code": errors,
            "p50_ms": pct_ms(out.latencies_s, 50), "p99_ms": pct_ms(out.latencies_s, 99),
            "bucket_s": out.bucket_s, "timeline": out.timeline()}


def restart_summary(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for kind in STOP_KINDS:
        mine = [r for r in rows if r["kind"] == kind]
        if mine:
            out[kind] = {"count": len(mine),
                         "stop_s_median": float(np.median([r["stop_s"] for r in mine])),
                         "stop_s_max": max(r["stop_s"] for r in mine),
                         "restart_s_median": float(np.median([r["restart_s"] for r in mine])),
                         "restart_s_max": max(r["restart_s"] for r in mine),
                         "clients_resumed_s_median": _median_or_none(
                             [r.get("clients_resumed_max_s") for r in mine]),
                         "clients_resumed_s_max": _max_or_none(
                             [r.get("clients_resumed_max_s") for r in mine]),
                         "exit_codes": sorted({r["exit_code"] for r in mine}),
                         "killed_after_timeout": sum(r["killed_after_timeout"] for r in mine)}
    return out


def _median_or_none(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return float(np.median(known)) if known else None


def _max_or_none(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return max(known) if known else None


def rss_summary(samples: Sequence[Sequence[Any]]) -> dict[str, Any]:
    values = [v for _, v in samples if v is not None]
    if not values:
        return {"samples": [list(s) for s in samples]}
    return {"first_mb": values[0], "median_mb": float(np.median(values)), "max_mb": max(values),
            "last_mb": values[-1], "samples": [list(s) for s in samples]}


# -- the table and the plot ----------------------------------------------------------------------

def table_lines(soak: Mapping[str, Any]) -> list[str]:
    """The soak's result as a Markdown table (one metric per row)."""
    q, k, r = soak["queries"], soak["keyframes"], soak["restart_summary"]
    errors = ", ".join(f"{c} {n}" for c, n in q["errors_by_code"].items()) or "none"
    rows = [("duration of the load", f"{soak['load_s']:.0f} s"),
            ("stops (kill -9 / SIGTERM), then a final one",
             f"{r.get('kill9', {}).get('count', 0)} / {r.get('sigterm', {}).get('count', 0)}"),
            ("queries sent / answered", f"{q['sent']} / {q['answered']}"),
            ("answered: ok / not relocalized", f"{q['ok']} / {q['not_relocalized']}"),
            ("errors by code", errors),
            ("latency while up, p50 / p99", f"{_ms(q['p50_ms'])} / {_ms(q['p99_ms'])}"),
            ("keyframes streamed: sent / acknowledged",
             f"{k['streamed_sent']} / {k['streamed_acknowledged']}"),
            ("deletes sent / acknowledged", f"{k['delete_sent']} / {k['delete_acknowledged']}"),
            ("keyframes held after the final restart", str(k["held_final"])),
            ("**keyframes lost** (checked after every restart and at the end)",
             f"**{k['lost']}**"),
            ("**keyframes duplicated**", f"**{k['duplicated']}**"),
            ("deleted keyframes back after a restart", str(k["resurrected"]))]
    for kind, label in (("kill9", "kill -9"), ("sigterm", "SIGTERM")):
        if kind in r:
            s = r[kind]
            rows.append((f"{label}: stop time median / max",
                         f"{s['stop_s_median']:.1f} / {s['stop_s_max']:.1f} s "
                         f"(exit codes {s['exit_codes']})"))
            rows.append((f"{label}: process start to first answer, median / max",
                         f"{s['restart_s_median']:.1f} / {s['restart_s_max']:.1f} s"))
            rows.append((f"{label}: then until every running client is answered, median / max",
                         f"{_s(s['clients_resumed_s_median'])} / "
                         f"{_s(s['clients_resumed_s_max'])}"))
    rss = soak["rss"]
    if "max_mb" in rss:
        rows.append(("service RSS: first / median / max / last",
                     f"{rss['first_mb']:.0f} / {rss['median_mb']:.0f} / {rss['max_mb']:.0f} / "
                     f"{rss['last_mb']:.0f} MB"))
    return ["| measure | value |", "|---|---|", *[f"| {a} | {b} |" for a, b in rows], ""]


def _s(value: Any) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.1f} s"


def _ms(value: Any) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.0f} ms"


def plot_rss(soak: Mapping[str, Any], path: Path) -> Path:
    """Resident memory of the service over the run and, below it, queries answered and
    failed per bucket (if recorded), with the stops marked."""
    from .plots import _pyplot, _save

    plt = _pyplot()
    timeline = soak.get("queries", {}).get("timeline")
    fig, axes = plt.subplots(2 if timeline else 1, 1, figsize=(9.5, 5.2 if timeline else 3.2),
                             sharex=True, squeeze=False)
    ax = axes[0][0]
    samples = soak["rss"]["samples"]
    ax.plot([t for t, _ in samples], [np.nan if v is None else v for _, v in samples],
            "-", lw=1.2, label="service RSS (MB)")
    ax.set(ylabel="MB", ylim=(0, None), title="reloc serve resident memory during the soak")
    if timeline:
        _plot_timeline(axes[1][0], timeline, soak["queries"]["bucket_s"],
                       soak.get("conf", {}).get("query_clients", "the"))
    for row in axes:
        _mark_stops(row[0], soak["restarts"])
        row[0].grid(True, alpha=0.3)
        row[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    axes[-1][0].set(xlabel="seconds into the run")
    return _save(fig, path)


def _plot_timeline(ax: Any, timeline: Sequence[Sequence[float]], bucket_s: float,
                   clients: Any) -> None:
    t = [row[0] for row in timeline]
    ax.bar(t, [row[1] for row in timeline], width=bucket_s, align="edge", color="tab:blue",
           label="answered")
    ax.bar(t, [row[2] for row in timeline], width=bucket_s, align="edge", color="tab:orange",
           bottom=[row[1] for row in timeline], label="no answer (busy, no reply, error)")
    ax.set(ylabel=f"queries per {bucket_s:.0f} s", title=f"queries of the {clients} clients")


def _mark_stops(ax: Any, restarts: Sequence[Mapping[str, Any]]) -> None:
    for kind, color, ls, label in (("kill9", "r", "--", "kill -9"),
                                   ("sigterm", "g", ":", "SIGTERM")):
        ats = [r["at_s"] for r in restarts if r["kind"] == kind]
        for n, at in enumerate(ats):
            ax.axvline(at, color=color, ls=ls, lw=1, label=label if n == 0 else None)
