"""The "Targets" table at the top of ``docs/performance.md``: each performance goal (latency of
the default method, its recall and wrong poses, speed against plain OpenCV, throughput, memory
at 1000 keyframes, ferns, no recall lost), its target, the value measured in this run and
whether it is met. Every cell is computed from
the run's result dict (never typed): a section that did not run gives "not measured"."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

#: Synthetic presets the default's recall must be checked on (besides every real set).
RECALL_PRESETS: tuple[str, ...] = ("room", "room-hard")
#: Recall the default may lose against ``sbi+p3p`` (percentage points), and its wrong rate.
RECALL_GAP_POINTS = 2.0
WRONG_MAX = 0.01
LARGEST_MAP_KEYFRAMES = 1000

Result = Mapping[str, Any]


def _num(value: Any) -> float | None:
    if value is None or isinstance(value, bool):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _get(d: Any, *keys: Any) -> Any:
    """``d[k0][k1]...`` or None where a key is missing (or a section recorded an error)."""
    for k in keys:
        if not isinstance(d, Mapping | Sequence) or isinstance(d, str):
            return None
        if isinstance(d, Mapping):
            if "error" in d or k not in d:
                return None
            d = d[k]
        else:
            if not isinstance(k, int) or not -len(d) <= k < len(d):
                return None
            d = d[k]
    return d


def row(item: str, target: str, measured: float | None, unit: str, ok: bool | None,
        detail: str = "") -> dict[str, Any]:
    """One table row; ``ok`` None: not measured in this run."""
    return {"item": item, "target": target, "measured": measured, "unit": unit,
            "met": None if measured is None else ok, "detail": detail}


def _at_most(value: float | None, limit: float) -> bool | None:
    return None if value is None else value <= limit


def _at_least(value: float | None, limit: float) -> bool | None:
    return None if value is None else value >= limit


# -- the rows ----------------------------------------------------------------------------------

def default_latency(r: Result) -> list[dict[str, Any]]:
    m = _get(r, "latency", "methods", "default")
    scene = r.get("scene") or {}
    where = (f"`{scene.get('preset')}` {scene.get('image')}, scale {scene.get('scale')}"
             if scene else "")
    p50 = _num(_get(m, "p50_ms"))
    over = _num(_get(m, "over_limit"))
    limit = _num(_get(r, "latency", "limit", "orb_limit_p50_ms"))
    # the target is on desk at 640x480: a smaller scene (a quick run) is shown, not judged
    target_scene = scene.get("preset") == "desk" and scene.get("image") == "640x480"
    if p50 is not None and not target_scene:
        where += " (not the target's scene: not judged)"
    return [row("default method p50 on desk 640x480 JPEG, decode included", "<= 30 ms", p50,
                "ms", _at_most(p50, 30.0) if target_scene else None, where),
            row("default method p50 / (decode + ORB extraction)", "<= 1.3x", over, "x",
                _at_most(over, 1.3), "" if limit is None else f"limit p50 {limit:.1f} ms")]


def default_recall(r: Result) -> list[dict[str, Any]]:
    """Recall within 2 points of ``sbi+p3p`` on room, room-hard and every real set; wrong
    poses at most 1% (every set scored, the latency scene included)."""
    acc = r.get("accuracy") or {}
    sets = {k: d for k, d in (_get(acc, "datasets") or {}).items() if "error" not in d}
    default = acc.get("default_method")
    gaps, wrong = {}, {}
    for name, d in sets.items():
        a, b = d["results"].get(default), d["results"].get("sbi+p3p")
        if a and b and "error" not in a and "error" not in b:
            gaps[name] = 100.0 * (a["recall"]["5cm_5deg"] - b["recall"]["5cm_5deg"])
        if a and "error" not in a:
            wrong[name] = a["wrong_rate"]
    desk_wrong = _num(_get(r, "latency", "methods", "default", "wrong_rate"))
    if desk_wrong is not None:
        wrong[f"latency scene ({(r.get('scene') or {}).get('preset')})"] = desk_wrong
    required = [p for p in RECALL_PRESETS if p not in gaps]
    required += [f"real set {k}" for k, d in sets.items()
                 if d.get("kind") == "real" and k not in gaps]
    real_note = [n for n in acc.get("notes", []) if n.startswith("real sets")]
    worst = min(gaps, key=lambda k: gaps[k]) if gaps else None
    detail = (f"worst: {worst}; " if worst else "") + ", ".join(
        f"{k} {v:+.0f}" for k, v in gaps.items())
    if required:
        detail += f"; not scored: {', '.join(required)}"
    if real_note:
        detail += "; " + "; ".join(real_note)
    gap = gaps[worst] if worst else None
    ok = None if required or gap is None else gap >= -RECALL_GAP_POINTS
    worst_wrong = max(wrong.values()) if wrong else None
    wrong_at = max(wrong, key=lambda k: wrong[k]) if wrong else ""
    return [row("default recall @5cm/5deg within 2 points of `sbi+p3p` (room, room-hard, "
                "every real set)", ">= -2 points", gap, "points",
                ok if gap is not None else None, detail),
            row("default wrong poses", "<= 1%", None if worst_wrong is None
                else 100.0 * worst_wrong, "%", _at_most(worst_wrong, WRONG_MAX),
                f"worst: {wrong_at}" if wrong else "")]


def plain_opencv(r: Result) -> list[dict[str, Any]]:
    ratio = _num(_get(r, "peers", "plain_opencv", "latency_over_ours"))
    ours = _num(_get(r, "peers", "ours", "recall", "5cm_5deg"))
    plain = _num(_get(r, "peers", "plain_opencv", "recall", "5cm_5deg"))
    ok = None
    if ratio is not None and ours is not None and plain is not None:
        ok = ratio >= 10.0 and ours >= plain
    detail = ("" if ours is None or plain is None
              else f"recall @5cm/5deg default {100 * ours:.0f}% vs plain {100 * plain:.0f}%")
    return [row("plain OpenCV p50 / default p50, at equal or better recall", ">= 10x", ratio,
                "x", ok, detail)]


def throughput(r: Result) -> list[dict[str, Any]]:
    t = r.get("throughput") or {}
    runs = _get(t, "runs") or []
    by = {x["clients"]: x for x in runs}
    one, eight = by.get(1), by.get(8)
    ratio = (eight["queries_per_s"] / one["queries_per_s"]
             if one and eight and one["queries_per_s"] else None)
    qps = _num(eight["queries_per_s"]) if eight else None
    where = (f"{t.get('workers')} workers, {t.get('mode')} mode, `{t.get('method')}`"
             if runs else "")
    every = [x for mode in (_get(t, "modes") or {}).values() for x in mode] or runs
    lost = sum(int(x.get("lost", 0)) for x in every) if every else None
    busy = sum(int(x.get("busy", 0)) for x in every) if every else 0
    counted = all("lost" in x for x in every)
    return [row("8 clients / 1 client, queries/s (2 workers)", ">= 1.8x", ratio, "x",
                _at_least(ratio, 1.8), where),
            row("8 clients, queries/s with the default method", ">= 40/s", qps, "/s",
                _at_least(qps, 40.0), where),
            row("busy replies explicit, none lost", "0 lost",
                None if lost is None or not counted else float(lost), "lost",
                None if lost is None or not counted else lost == 0,
                f"{busy} busy replies counted over every run and mode" if every else "")]


def memory(r: Result) -> list[dict[str, Any]]:
    sizes = [s for s in (_get(r, "scaling", "sizes") or []) if "error" not in s]
    big = max(sizes, key=lambda s: s["keyframes"]) if sizes else None
    at = big is not None and big["keyframes"] >= LARGEST_MAP_KEYFRAMES
    methods = ", ".join(f"`{m}`" for m in (_get(r, "scaling", "methods") or []))
    where = (f"{big['keyframes']} keyframes, {big['landmarks']} landmarks; models of "
             f"{methods}" if big else "")
    if big is not None and not at:
        where += f" (largest map below {LARGEST_MAP_KEYFRAMES}: not the target's size)"

    def value(key: str) -> float | None:
        return _num(big.get(key)) if at and big else None

    rss, load, snap = value("map_rss_mb"), value("engine_load_s"), value("snapshot_mb")
    return [row("1000 keyframes: resident memory of the map and the default's models",
                "<= 120 MB", rss, "MB", _at_most(rss, 120.0), where),
            row("1000 keyframes: `Engine.load`", "<= 0.5 s", load, "s", _at_most(load, 0.5),
                where),
            row("1000 keyframes: snapshot on disk", "<= 50 MB", snap, "MB",
                _at_most(snap, 50.0), where)]


def ferns(r: Result) -> list[dict[str, Any]]:
    sweep = _get(r, "ferns", "classes_sweep") or {}
    hit = [x for x in sweep.get("rows", []) if x["classes"] == 2000] \
        if sweep.get("keypoints") == 500 else []
    ms = _num(hit[0]["total_ms"]) if hit else None
    room = _get(r, "accuracy", "datasets", "room", "results") or {}
    f, s = room.get("ferns"), room.get("sbi+p3p")
    ratio, times = None, ""
    if f and s and "error" not in f and "error" not in s and s["p50_ms"]:
        ratio = f["p50_ms"] / s["p50_ms"]
        times = f"{f['p50_ms']:.0f} ms vs {s['p50_ms']:.0f} ms"
    return [row("ferns: 500 keypoints x 2000 classes p50", "<= 20 ms", ms, "ms",
                _at_most(ms, 20.0), "" if hit else "2000 classes not in this run's sweep"),
            row("ferns: room p50 / `sbi+p3p` room p50", "<= 1.5x", ratio, "x",
                _at_most(ratio, 1.5), times)]


def recall_changes(r: Result, baseline: Result) -> list[dict[str, Any]]:
    """Every recall of ``baseline``'s accuracy section that this run scored too (same dataset,
    same method, every threshold both recorded): before, after and the change in points. Datasets or methods
    scored in only one of the runs, or failed in either, are left out."""
    now = _get(r, "accuracy", "datasets") or {}
    before = _get(baseline, "accuracy", "datasets") or {}
    out = []
    for name in [k for k in before if k in now]:
        b_res, a_res = _get(before, name, "results") or {}, _get(now, name, "results") or {}
        for method in [m for m in b_res if m in a_res]:
            b, a = b_res[method], a_res[method]
            if not isinstance(b, Mapping) or not isinstance(a, Mapping) or "error" in b \
                    or "error" in a:
                continue
            for t in [t for t in b.get("recall") or {} if t in (a.get("recall") or {})]:
                rb, ra = _num(b["recall"][t]), _num(a["recall"][t])
                if rb is not None and ra is not None:
                    out.append({"dataset": name, "method": method, "recall": t,
                                "before": rb, "after": ra, "points": 100.0 * (ra - rb)})
    return out


def no_recall_lost(r: Result, baseline: Result | None = None) -> list[dict[str, Any]]:
    """Every recall scored by both this run and ``baseline`` (a run of the code before a
    change, ``reloc bench --baseline OLD.json``) must not fall; the worst change is shown."""
    item, target = "no recall lost anywhere (eval tables before and after)", "before <= after"
    if baseline is None:
        return [row(item, target, None, "", None,
                    "needs the accuracy tables of a run before the change: "
                    "`reloc bench --baseline BEFORE.json`")]
    changes = recall_changes(r, baseline)
    if not changes:
        return [row(item, target, None, "", None,
                    "the baseline and this run scored no dataset and method in common")]
    worst = min(changes, key=lambda c: c["points"])
    lost = [c for c in changes if c["points"] < 0]
    sets = sorted({c["dataset"] for c in changes})
    detail = (f"{len(changes)} recalls compared on {', '.join(sets)} against "
              f"{baseline.get('code', {}).get('commit') or 'the baseline'}; ")
    detail += ("lost: " + ", ".join(f"{c['dataset']} `{c['method']}` @{c['recall']} "
                                    f"{c['points']:+.1f}" for c in lost)
               if lost else f"worst: {worst['dataset']} `{worst['method']}` "
                            f"@{worst['recall']} {worst['points']:+.1f}")
    return [row(item, target, worst["points"], "points", not lost, detail)]


ROWS: tuple[Callable[[Result], list[dict[str, Any]]], ...] = (
    default_latency, default_recall, plain_opencv, throughput, memory, ferns)


def targets(result: Result, baseline: Result | None = None) -> list[dict[str, Any]]:
    """Every row of the table, in the order of :data:`ROWS`; the last one compares this run's
    accuracy tables with ``baseline``'s (a run before the change)."""
    return [x for fn in ROWS for x in fn(result)] + no_recall_lost(result, baseline)


def _value(x: Mapping[str, Any]) -> str:
    v = x["measured"]
    if v is None:
        return "-"
    digits = 0 if x["unit"] in ("lost", "points") or abs(v) >= 100 else (
        1 if abs(v) >= 10 or x["unit"] == "%" else 2)
    unit = {"x": "x", "%": "%", "/s": "/s"}.get(x["unit"], f" {x['unit']}" if x["unit"] else "")
    sign = "+" if x["unit"] == "points" and v > 0 else ""
    return f"{sign}{v:.{digits}f}{unit}"


def markdown_lines(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The table (goal, target, measured, met / not met / not measured)."""
    verdict = {True: "**met**", False: "**not met**", None: "not measured"}
    out = ["| goal | target | measured | | notes |", "|---|---|---|---|---|"]
    for x in rows:
        out.append(f"| {x['item']} | {x['target']} | {_value(x)} | {verdict[x['met']]} | "
                   f"{x['detail']} |")
    met = sum(x["met"] is True for x in rows)
    return out + ["", f"{met} of {len(rows)} met; "
                      f"{sum(x['met'] is None for x in rows)} not measured in this run.", ""]
