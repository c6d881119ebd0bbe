"""``reloc bench --only attack``: the attacks of docs/reliability.md as a suite (a benchmark, not
CI), each judged per attempt as *clean* or *broke something*.

Every case starts real ``reloc serve`` processes (a Zenoh peer on a free loopback port, multicast
scouting off, storage in a temporary folder), attacks them over real Zenoh sessions or on their
files on disk, and judges each attempt:

- **clean**: refused with the error code (or rejection event) the protocol names for it, or
  survived: nothing acknowledged lost, no content served that was not put, and the service still
  answers ``status`` afterwards;
- **broke**: an INTERNAL error, another code than the one named, no reply (a hang), a crash,
  an acknowledged keyframe lost, damaged or foreign content served.

Cases are registered explicitly in :data:`CASES` with their group (:data:`GROUPS`);
:func:`run_attack` runs them (all, or those named) and returns the JSON section;
:func:`table_lines` prints the table. Keyframes are tiny synthetic images (160x120 textured
noise), so the whole suite runs in a few minutes on a loaded two-core machine.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

# The case modules register their cases in CASES on import.
from . import input_cases, quota_cases, replica_cases, restore_cases, storage_cases
from .harness import (
    CASES,
    GROUPS,
    Arena,
    Attempt,
    Case,
    broke,
    clean,
    compare_held,
    judge_code,
    register,
    tiny_scene,
)
from .input_cases import nested, request_with

__all__ = ["CASES", "GROUPS", "Arena", "Attempt", "Case", "clean", "broke", "compare_held",
           "judge_code", "register", "tiny_scene", "nested", "request_with", "run_case",
           "run_attack", "table_lines", "run_into", "input_cases", "quota_cases",
           "replica_cases", "restore_cases", "storage_cases"]


# -- the run -------------------------------------------------------------------------------------

def run_case(case: Case, arena: Arena) -> dict[str, Any]:
    """Run ``case``; then the shared service must still answer. A case that raises broke
    something (its exception is the detail)."""
    start = time.perf_counter()
    try:
        attempts = case.run(arena)
    except Exception as exc:  # an attack the harness could not finish is reported, not hidden
        traceback.print_exc()
        attempts = [broke(f"{type(exc).__name__}: {exc}")]
    if case.group == "input" and "input" in arena.shared:
        problem = arena.shared["input"].answers()
        if problem is not None:
            attempts.append(broke(f"after the case: {problem}"))
    n_clean = sum(a.clean for a in attempts)
    return {"case": case.name, "group": case.group, "summary": case.summary,
            "attempts": len(attempts), "clean": n_clean, "broke": len(attempts) - n_clean,
            "details": [{"clean": a.clean, "detail": a.detail} for a in attempts],
            "seconds": time.perf_counter() - start}


def run_attack(names: Sequence[str] | None = None, *, workdir: Path | None = None,
               on_progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the cases ``names`` (default: all of :data:`CASES`, group by group); the JSON section:
    one row per case and the totals."""
    unknown = sorted(set(names or ()) - set(CASES))
    if unknown:
        raise ValueError(f"unknown attack case(s) {unknown}; expected some of {list(CASES)}")
    say = on_progress or (lambda _m: None)
    started = time.perf_counter()
    with contextlib.ExitStack() as stack:
        folder = workdir or Path(stack.enter_context(
            tempfile.TemporaryDirectory(prefix="reloc-attack-")))
        folder.mkdir(parents=True, exist_ok=True)
        arena = Arena(folder, tiny_scene())
        stack.callback(arena.close)
        rows = []
        for name in names or by_group():
            row = run_case(CASES[name], arena)
            rows.append(row)
            say(f"attack {name}: {row['attempts']} attempts, {row['clean']} clean, "
                f"{row['broke']} broke ({row['seconds']:.1f} s)")
    totals = {k: sum(r[k] for r in rows) for k in ("attempts", "clean", "broke")}
    return {"cases": rows, **totals, "seconds": time.perf_counter() - started,
            "groups": {g: [c.name for c in CASES.values() if c.group == g] for g in GROUPS}}


def by_group() -> list[str]:
    """Every case name, the groups in :data:`GROUPS` order (each group's cases as registered)."""
    return sorted(CASES, key=lambda name: GROUPS.index(CASES[name].group))


def table_lines(attack: Mapping[str, Any]) -> list[str]:
    """The attack's result as a Markdown table (a case per row; the first attempt that broke
    something, else the first attempt's detail) and the totals."""
    rows = ["| case | group | attempts | clean | broke | detail |", "|---|---|---|---|---|---|"]
    for r in attack["cases"]:
        details = r["details"]
        shown = next((d for d in details if not d["clean"]), details[0] if details else None)
        text = "" if shown is None else shorten(shown["detail"]).replace("|", "\\|")
        rows.append(f"| {r['case']} | {r['group']} | {r['attempts']} | {r['clean']} | "
                    f"{r['broke']} | {text} |")
    return [*rows, "", f"attempts / clean / broke something: {attack['attempts']} / "
                       f"{attack['clean']} / {attack['broke']}", ""]


def shorten(text: str, limit: int = 200) -> str:
    """``text`` cut to ``limit`` characters for a table cell (the JSON keeps it whole)."""
    return text if len(text) <= limit else text[:limit - 3] + "..."


def run_into(result: dict[str, Any], workdir: Path | None, say: Callable[[str], None]) -> None:
    """Run every case into ``result["attack"]`` (an ``{"error": ...}`` if the run failed)."""
    from ...eval.results import json_safe

    try:
        result["attack"] = json_safe(run_attack(workdir=workdir and workdir / "attack",
                                                on_progress=say))
    except Exception as exc:  # the error is the section's result, as for the others
        traceback.print_exc()
        result["attack"] = {"error": f"{type(exc).__name__}: {exc}"}
        return
    result.setdefault("section_seconds", {})["attack"] = result["attack"]["seconds"]

