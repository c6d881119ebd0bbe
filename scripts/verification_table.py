"""The "no confident wrong pose" table from ``reloc eval --json`` files: per set and method,
recall within 5 cm / 5 deg and 25 cm / 10 deg, answers beyond 25 cm / 10 deg and beyond
50 cm / 15 deg (the wrong poses), refusals, and ``cov scale`` — with the change against an
earlier run of the same sets when one is given.

    python scripts/verification_table.py AFTER_DIR [--before BEFORE_DIR] [--order a,b,c]

Each directory holds one ``NAME.json`` per set (the output of ``reloc eval SET --json
NAME.json``); sets are matched by file name. Counts are of queries, rates of all queries,
as ``reloc eval`` reports them.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

#: (translation metres, rotation degrees): an answer beyond it is "off"; beyond the second, wrong.
OFF = (0.25, 10.0)
WRONG = (0.50, 15.0)


def _beyond(query: dict[str, Any], limit: tuple[float, float]) -> bool:
    """An answer whose translation or rotation error exceeds ``limit``."""
    if not query.get("returned"):
        return False
    return bool(query["t_err_m"] > limit[0] or query["r_err_deg"] > limit[1])


def row(method: dict[str, Any]) -> dict[str, Any]:
    """The table's figures of one method of one eval run."""
    queries = method["queries"]
    summary = method["summary"]
    return {
        "method": method["method"],
        "queries": len(queries),
        "answered": sum(1 for q in queries if q.get("returned")),
        "recall_5": summary["recall"]["5cm_5deg"],
        "recall_25": summary["recall"]["25cm_10deg"],
        "off": sum(_beyond(q, OFF) for q in queries),
        "wrong": sum(_beyond(q, WRONG) for q in queries),
        "cov_scale": summary.get("covariance_scale"),
    }


def load(directory: Path) -> dict[str, list[dict[str, Any]]]:
    """Set name -> one row per method, from every ``*.json`` eval file in ``directory``."""
    out: dict[str, list[dict[str, Any]]] = {}
    for path in sorted(directory.glob("*.json")):
        data = json.loads(path.read_text())
        if "methods" not in data:
            raise SystemExit(f"{path}: expected a `reloc eval --json` file (no 'methods' field)")
        out[path.stem] = [row(m) for m in data["methods"]]
    return out


def _pct(x: float) -> str:
    return f"{100 * x:.0f}%"


def _cov(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def _delta(after: float, before: float | None) -> str:
    if before is None:
        return ""
    points = round(100 * (after - before))
    return "" if points == 0 else f" ({points:+d})"


def _was(before: dict[str, Any] | None, key: str, fmt: Any) -> str:
    return "" if before is None else f" (was {fmt(before[key])})"


def render(after: dict[str, list[dict[str, Any]]], before: dict[str, list[dict[str, Any]]],
           order: list[str]) -> str:
    """A Markdown table; a bracket after a figure gives the change against ``before``."""
    lines = ["| set | method | answered | recall 5cm/5deg | recall 25cm/10deg | beyond 25cm/10deg "
             "| wrong (>50cm/15deg) | cov scale |", "|---|---|---|---|---|---|---|---|"]
    names = [n for n in order if n in after] + sorted(n for n in after if n not in order)
    for name in names:
        earlier = {r["method"]: r for r in before.get(name, [])}
        for r in after[name]:
            b = earlier.get(r["method"])
            cells = [name, f"`{r['method']}`", f"{r['answered']}/{r['queries']}",
                     _pct(r["recall_5"]) + _delta(r["recall_5"], None if b is None else b["recall_5"]),
                     _pct(r["recall_25"]) + _delta(r["recall_25"], None if b is None else b["recall_25"]),
                     str(r["off"]) + _was(b, "off", str), str(r["wrong"]) + _was(b, "wrong", str),
                     _cov(r["cov_scale"]) + _was(b, "cov_scale", _cov)]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("after", type=Path, help="directory of reloc eval JSON files, one per set")
    ap.add_argument("--before", type=Path, help="an earlier run's directory, same file names")
    ap.add_argument("--order", default="", help="comma-separated set names to list first")
    args = ap.parse_args(argv)
    before = load(args.before) if args.before else {}
    print(render(load(args.after), before, [n for n in args.order.split(",") if n]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
