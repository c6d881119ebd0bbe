"""Lines of code the service needs at run time: the first-party modules ``reloc serve`` can
import (statically, function-level imports and ``importlib`` strings included, read by the
architecture test's reader tests/archcheck.py), against the tools' lines and the whole.

    python scripts/runtime_lines.py [--root CHECKOUT] [--list]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # one import-graph reader: the architecture test's

from archcheck import Module, closure, load  # noqa: E402

#: ``reloc serve``: the CLI's entry, its serve subcommand and the module that implements it
#: (imported inside the subcommand's functions, which the reader follows).
SERVE_ROOTS = ("reloc_service.cli.main", "reloc_service.cli.serve", "reloc_service.service.cli")
#: The tools, where they live now and where they lived before moving under tools/ (957bde1).
TOOLS = ("reloc_service.tools", "reloc_service.eval", "reloc_service.data", "reloc_service.synth",
         "reloc_service.bench", "reloc_service.service.demo")


def non_blank_lines(path: Path) -> int:
    return sum(1 for line in path.read_text(encoding="utf-8").splitlines() if line.strip())


def is_tool(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in TOOLS)


def summary(modules: dict[str, Module], names: set[str]) -> tuple[int, int]:
    """(module count, non-blank lines) of ``names``."""
    return len(names), sum(non_blank_lines(modules[n].path) for n in names)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=REPO, help="checkout to measure "
                        "(default: this one)")
    parser.add_argument("--list", action="store_true", help="list the runtime modules")
    args = parser.parse_args(argv)
    modules, graph = load(args.root)
    missing = [r for r in SERVE_ROOTS if r not in modules]
    if missing:
        print(f"runtime_lines: {args.root} has no {', '.join(missing)}", file=sys.stderr)
        return 2
    runtime = closure(graph, SERVE_ROOTS)
    rows = [("reloc serve needs at run time", runtime),
            ("  of which tools", {n for n in runtime if is_tool(n)}),
            ("tools (eval, data, synth, bench, demo)", {n for n in modules if is_tool(n)}),
            ("all first-party modules", set(modules))]
    for label, names in rows:
        count, lines = summary(modules, names)
        print(f"{label:40s} {count:4d} modules {lines:6d} lines (non-blank)")
    unseen = [f"{m.name}:{line}" for m in modules.values() if m.name in runtime
              for line in m.unresolved]
    if unseen:
        print(f"dynamic imports not followed (the serve path through them is SERVE_ROOTS): "
              f"{', '.join(unseen)}")
    if args.list:
        print("\n".join(sorted(runtime)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
