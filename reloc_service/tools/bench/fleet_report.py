"""The fleet section (:mod:`.fleet`) as text: its table for the terminal and for
docs/performance.md, and whether the run failed (a query not answered)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

#: The start-up the fleet target asks for: process start to the first answer.
STARTUP_TARGET_S = 2.0


def _f(value: Any, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def _pct(value: Any) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else f"{100 * value:.0f}%"


def failure(section: Mapping[str, Any]) -> str | None:
    """Why a fleet run that ran failed (queries lost or refused), or None."""
    f = section.get("fleet", {})
    bad = int(f.get("lost", 0)) + len(f.get("errors", []))
    return f"{bad} queries not answered" if bad else None


def _accuracy(run: Mapping[str, Any]) -> str:
    recall = run.get("recall", {})
    return (f"{_pct(recall.get('5cm_5deg'))} / {_pct(recall.get('25cm_10deg'))} / "
            f"{_pct(run.get('wrong_rate'))} / {_f(run.get('cov_scale'), 2)}")


def table_lines(section: Mapping[str, Any]) -> list[str]:
    """The fleet run against the baseline, one row per figure (Markdown table)."""
    base, fleet, t = section["baseline"], section["fleet"], section["template"]
    rss, acc = fleet["rss"], fleet["accounting"]
    budget = fleet["budget_mb"]
    rows = [
        ("maps x keyframes (landmarks each)",
         f"1 x {t['keyframes']} ({t['landmarks']})",
         f"{section['maps']} x {t['keyframes']} ({t['landmarks']})"),
        ("`max_resident_mb`", "0 (always resident)", _f(budget, 0)),
        ("start-up to the first answer", f"{_f(base['startup_to_first_answer_s'], 2)} s",
         f"{_f(fleet['startup_to_first_answer_s'], 2)} s (a cold load included; target "
         f"<= {STARTUP_TARGET_S:g} s{'; bytecode compiled' if 'bytecode' in section else ''})"),
        ("queries answered / busy replies / lost / errors",
         f"{base['answered']} / {base['busy_replies']} / {base['lost']} / "
         f"{len(base['errors'])}",
         f"{fleet['answered']} / {fleet['busy_replies']} / {fleet['lost']} / "
         f"{len(fleet['errors'])}"),
        ("warm queries: n, p50, p99 (ms)",
         f"{base['warm']['n']}, {_f(base['warm']['p50_ms'])}, {_f(base['warm']['p99_ms'])}",
         f"{fleet['warm']['n']}, {_f(fleet['warm']['p50_ms'])}, "
         f"{_f(fleet['warm']['p99_ms'])} ({_f(section.get('warm_p50_over_baseline'), 2)}x "
         f"the baseline's p50; {_f(section.get('warm_over_baseline_by_image'), 2)}x the "
         "baseline's time for the same image, median)"),
        ("cold queries: n, p50, p99, max (ms)", "-",
         f"{fleet['cold']['n']}, {_f(fleet['cold']['p50_ms'])}, {_f(fleet['cold']['p99_ms'])}, "
         f"{_f(fleet['cold']['max_ms'])}"),
        ("cold loads: n, p50, max (s)", "-",
         f"{acc['loads']}, {_f(acc['load_p50_s'], 2)}, {_f(acc['load_max_s'], 2)}"),
        ("counted MB resident: max after a close, after a load", "-",
         f"{_f(acc['max_after_close_mb'])}, {_f(acc['max_after_load_mb'])} (a map is "
         f"{_f(t['counted_mb'])} MB counted)"),
        ("maps resident (liveliness): max, at the end", "-",
         f"{fleet['resident_maps_max']}, {fleet['resident_maps_at_end']}"),
        ("RSS of the service: at the first answer, p50, max (MB)", "-",
         f"{_f(fleet['rss_at_first_answer_mb'], 0)}, {_f(rss['p50_mb'], 0)}, "
         f"{_f(rss['max_mb'], 0)} ({_f(fleet['max_rss_over_budget'], 2)}x the budget)"),
        ("recall 5cm/5deg / 25cm/10deg / wrong / cov scale", _accuracy(base), _accuracy(fleet)),
    ]
    rows += _pool_rows(section.get("repetition_pool", {}))
    lines = ["| | baseline | fleet |", "|---|---|---|"]
    return lines + [f"| {a} | {b} | {c} |" for a, b, c in rows] + [""]


def _pool_rows(pool: Mapping[str, Any]) -> list[tuple[str, str, str]]:
    """The repetition check's pool of the template, per kind: its size, the index's build
    and one query's search against a full scan of it (:mod:`.fleet_pool`)."""
    return [(f"repetition check, {kind.upper()} pool of the template: rows (MB), index build "
             "(s), one query's search / full scan (ms), ratio-test matches found",
             f"{p['rows']} ({_f(p['pool_mb'])} MB)",
             f"{_f(p['index_build_s'], 2)}, {_f(p.get('search_ms_p50'))} / "
             f"{_f(p.get('full_scan_ms_p50'))}, {_pct(p.get('ratio_matches_found'))}"
             + ("" if p.get("indexed") else " (scanned in full)"))
            for kind, p in pool.items()]


def markdown_lines(section: Mapping[str, Any]) -> list[str]:
    """docs/performance.md's fleet section."""
    t, conf, disk = section["template"], section["conf"], section["storage"]
    return ["## Many maps, bounded memory (fleet)", "",
            f"One template map ({t['keyframes']} keyframes of {t['image']}: the "
            f"`{t['preset']}` scene's {t['scene_keyframes']} keyframes grown with distractor "
            f"keyframes as in the scaling section; {_f(t['disk_mb'])} MB on disk, "
            f"{_f(t['counted_mb'])} MB counted once loaded) copied {section['maps']} times "
            f"into one storage (snapshot files hard-linked: {_f(disk['apparent_mb'], 0)} MB "
            f"apparent, {_f(disk['on_disk_mb'], 0)} MB on disk; removed afterwards). "
            f"One `reloc serve` ({conf['workers']} {conf['worker_mode']} workers, "
            f"`cold_load_wait_s = {conf['cold_load_wait_s']:g}`) serves them with "
            f"`max_resident_mb = {_f(section['fleet']['budget_mb'], 0)}`; "
            f"{conf['queries']} times a map and a query are picked at random and the query "
            "is sent twice: the first is cold when the map was not resident, the second "
            "warm. The baseline is the same service serving one copy, always resident. "
            "RSS is the service process and its children, sampled every "
            f"{conf['rss_period_s']:g} s; counted MB is the residency manager's own "
            "accounting (its log), which the budget bounds (a map just loaded counts before "
            "the least recently used one is closed). Recall, wrong poses and cov scale "
            "are over every answer.", "", *table_lines(section)]
