"""Compare two ``reloc eval --json`` results query by query: what a change did to the answers.

A query differs when its status, refusal reason, answering step or inlier count changed, or its
position error moved by more than ``--tol-m`` (1 mm) or its rotation error by more than
``--tol-deg``; the summary line gives recall at 5 cm / 5 deg, the wrong-pose rate, cov scale
and how many answers lie beyond 3 sigma (position Mahalanobis length > 3; a 3-D Gaussian puts
2.9 % there) before and after. Methods are paired by name.

    python3 scripts/compare_eval.py BEFORE.json AFTER.json
    python3 scripts/compare_eval.py BEFORE_DIR AFTER_DIR     # every SET.json the two share

Exit status 1 when any query differs, so a claimed answer-identical change can be checked in a
script.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

#: Fields whose any change makes a query differ.
_EXACT = ("status", "reason", "method_used", "inliers")


def _differences(before: dict[str, Any], after: dict[str, Any], tol_m: float,
                 tol_deg: float) -> list[str]:
    """What changed between one query's two results, as ``field: old -> new``."""
    out = [f"{k}: {before.get(k)} -> {after.get(k)}" for k in _EXACT
           if before.get(k) != after.get(k)]
    for key, tol in (("t_err_m", tol_m), ("r_err_deg", tol_deg)):
        x, y = before.get(key), after.get(key)
        if (x is None) != (y is None) or (x is not None and abs(x - y) > tol):
            out.append(f"{key}: {x} -> {y}")
    return out


def _beyond_3_sigma(queries: list[dict[str, Any]]) -> tuple[int, int]:
    """(answers with a position Mahalanobis length, those of them beyond 3)."""
    lengths = [q["t_err_mahalanobis"] for q in queries if q.get("t_err_mahalanobis") is not None]
    return len(lengths), sum(1 for v in lengths if v > 3)


def _fmt(value: float | None) -> str:
    return "none" if value is None else f"{value:.2f}"


def _summary(method: dict[str, Any]) -> str:
    s = method["summary"]
    scored, beyond = _beyond_3_sigma(method["queries"])
    return (f"recall5 {s['recall']['5cm_5deg']:.3f} wrong {s['wrong_rate']:.3f} "
            f"cov {_fmt(s.get('covariance_scale'))} beyond3 {beyond}/{scored}")


def compare_files(before_path: Path, after_path: Path, tol_m: float, tol_deg: float) -> int:
    """Print the differing queries of every method the two files share; their number."""
    before = {m["method"]: m for m in json.loads(before_path.read_text())["methods"]}
    after = {m["method"]: m for m in json.loads(after_path.read_text())["methods"]}
    total = 0
    for name in before.keys() & after.keys():
        qa, qb = before[name]["queries"], after[name]["queries"]
        if len(qa) != len(qb):
            print(f"{after_path.stem} {name}: {len(qa)} queries before, {len(qb)} after")
            total += max(len(qa), len(qb))
            continue
        differ = 0
        for i, (x, y) in enumerate(zip(qa, qb, strict=True)):
            changes = _differences(x, y, tol_m, tol_deg)
            if changes:
                differ += 1
                print(f"{after_path.stem} {name} q{i}: " + "; ".join(changes))
        total += differ
        print(f"{after_path.stem} {name}: {len(qa)} queries, {differ} differ; "
              f"{_summary(before[name])} -> {_summary(after[name])}")
    return total


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", type=Path, help="an eval JSON, or a directory of SET.json")
    parser.add_argument("after", type=Path, help="the same, after the change")
    parser.add_argument("--tol-m", type=float, default=1e-3,
                        help="position error change that counts as a difference (metres)")
    parser.add_argument("--tol-deg", type=float, default=0.1,
                        help="rotation error change that counts as a difference (degrees)")
    args = parser.parse_args(argv)
    if args.before.is_dir() != args.after.is_dir():
        parser.error("expected two files or two directories")
    if args.before.is_dir():
        names = sorted({p.name for p in args.before.glob("*.json")}
                       & {p.name for p in args.after.glob("*.json")})
        if not names:
            parser.error(f"no SET.json common to {args.before} and {args.after}")
        pairs = [(args.before / n, args.after / n) for n in names]
    else:
        pairs = [(args.before, args.after)]
    total = sum(compare_files(a, b, args.tol_m, args.tol_deg) for a, b in pairs)
    print(f"{len(pairs)} set(s), {total} queries differ")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
