"""Run reloc's commands N times each on the real sets and tabulate how they exit.

    .venv/bin/python scripts/exit_runs.py --runs 20 --command eval --command serve \\
        --out out/exit_runs

``eval``: ``reloc eval SET`` with the default chain, the sets taken in turn. ``serve``:
``reloc serve`` on a storage directory per set (the set's map uploaded and trained through
``reloc-client`` the first time, restored from storage afterwards), one query relocalized,
then SIGTERM. ``demo``: ``reloc demo``. ``bench-quick``: ``reloc bench --quick``. A run is
clean when it exits 0 and its stderr holds none of :data:`ABNORMAL`; the stderr of every
other run is kept in OUT. Prints a Markdown table (and writes it to OUT/table.md)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
#: ``shared/data/real`` beside the repository (a checkout) or beside its parent (a worktree).
REAL = next((p for p in (ROOT.parent / "shared" / "data" / "real",
                         ROOT.parent.parent / "shared" / "data" / "real") if p.is_dir()),
            ROOT.parent / "shared" / "data" / "real")
REAL_SETS = ("tum_fr1_rpy", "7scenes_redkitchen", "strecha_fountain_p11",
             "strecha_herzjesu_p25")

#: What an abnormal end leaves on stderr: glibc's and the C++ runtime's abort messages, an
#: uncaught Python exception, serve leaving threads of ours behind.
ABNORMAL = ("FATAL", "Abort", "terminate called", "Traceback", "Fatal Python error",
            "exiting without waiting for")


@dataclass
class Run:
    code: int
    seconds: float
    marks: list[str]
    stderr: str


@dataclass
class Tally:
    runs: list[Run] = field(default_factory=list)

    def row(self, name: str) -> str:
        codes: dict[int, int] = {}
        for r in self.runs:
            codes[r.code] = codes.get(r.code, 0) + 1
        other = ", ".join(f"{c}: {n}" for c, n in sorted(codes.items()) if c != 0) or "-"
        marked = sum(bool(r.marks) for r in self.runs)
        clean = sum(r.code == 0 and not r.marks for r in self.runs)
        median = statistics.median(r.seconds for r in self.runs)
        return (f"| {name} | {len(self.runs)} | {codes.get(0, 0)} | {other} | {marked} | "
                f"{clean} | {median:.0f} |")


def marks_in(stderr: str) -> list[str]:
    return [word for word in ABNORMAL if word in stderr]


def timed(argv: list[str], timeout: float, cwd: Path) -> Run:
    start = time.monotonic()
    proc = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    return Run(proc.returncode, time.monotonic() - start, marks_in(proc.stderr), proc.stderr)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_eval(k: int, sets: list[Path], work: Path) -> Run:
    dataset = sets[k % len(sets)]
    return timed([str(BIN / "reloc"), "eval", str(dataset), "--no-progress",
                  "--json", str(work / f"eval-{k}.json")], 1800, work)


def run_demo(k: int, sets: list[Path], work: Path) -> Run:
    return timed([str(BIN / "reloc"), "demo"], 1800, work)


def run_bench_quick(k: int, sets: list[Path], work: Path) -> Run:
    return timed([str(BIN / "reloc"), "bench", "--quick", "--json",
                  str(work / f"bench-{k}.json")], 3600, work)


def serve_config(directory: Path, port: int) -> Path:
    path = directory / "service.toml"
    path.write_text("\n".join([
        "[zenoh]", 'mode = "peer"', f'listen = ["tcp/127.0.0.1:{port}"]',
        "multicast_scouting = false", "[service]", 'instance = "exit-runs"',
        f'storage = "{directory / "storage"}"',
        # the Strecha sets' 1536x1024 images, above the companion-sized default
        "[limits]", f"max_image_pixels = {1536 * 1024}", "[maps.lab]", ""]))
    return path


def client(port: int, *argv: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN / "reloc-client"), "--connect", f"tcp/127.0.0.1:{port}",
                           "--map", "lab", "--timeout", "60", *argv],
                          capture_output=True, text=True, timeout=timeout)


def first_query(dataset: Path) -> tuple[Path, str]:
    for line in (dataset / "queries.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            image, camera_id = line.split()[:2]
            return dataset / image, camera_id
    raise ValueError(f"{dataset}/queries.txt: expected a query line")


def run_serve(k: int, sets: list[Path], work: Path) -> Run:
    """``reloc serve`` on the set's storage; upload and train the first time; one query;
    SIGTERM. The client's failures count as the run's (a service that cannot answer)."""
    dataset = sets[k % len(sets)]
    directory = work / f"serve-{dataset.name}"
    directory.mkdir(parents=True, exist_ok=True)
    fresh = not (directory / "storage").exists()
    port = free_port()
    start = time.monotonic()
    proc = subprocess.Popen([str(BIN / "reloc"), "serve", "--config",
                             str(serve_config(directory, port))],
                            cwd=work, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    problems = []
    try:
        deadline = time.monotonic() + 300
        while client(port, "status", timeout=120).returncode != 0:
            if proc.poll() is not None or time.monotonic() > deadline:
                problems.append("the service never answered status")
                break
            time.sleep(0.5)
        if not problems and fresh:
            up = client(port, "upload", str(dataset), "--train", "--wait", timeout=1800)
            if up.returncode != 0:
                problems.append(f"upload: {up.stderr[-500:]}")
        if not problems:
            image, camera_id = first_query(dataset)
            asked = client(port, "relocalize", str(image), "--camera-id", camera_id)
            if asked.returncode != 0:
                problems.append(f"relocalize: {asked.stderr[-500:]}")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            _, stderr = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, stderr = proc.communicate()
            problems.append("did not stop within 120 s of SIGTERM")
    marks = marks_in(stderr) + problems
    return Run(proc.returncode, time.monotonic() - start, marks, stderr + "\n".join(problems))


def write_outputs(work: Path, tallies: dict[str, Tally]) -> None:
    """OUT/table.md (the Markdown table) and OUT/runs.json (every run's exit and marks)."""
    lines = ["| command | runs | exit 0 | other exits (code: runs) | abnormal stderr | clean | "
             "median s |", "|---|---|---|---|---|---|---|",
             *[tally.row(name) for name, tally in tallies.items()]]
    (work / "table.md").write_text("\n".join(lines) + "\n")
    (work / "runs.json").write_text(json.dumps(
        {name: [{"code": r.code, "seconds": r.seconds, "marks": r.marks} for r in t.runs]
         for name, t in tallies.items()}, indent=1))


COMMANDS: dict[str, Callable[[int, list[Path], Path], Run]] = {
    "eval": run_eval, "serve": run_serve, "demo": run_demo, "bench-quick": run_bench_quick}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=20, help="runs of each command")
    parser.add_argument("--command", action="append", choices=sorted(COMMANDS),
                        help="command to run (repeatable; default: all)")
    parser.add_argument("--dataset", action="append", type=Path,
                        help=f"set to use in turn (default: the real sets of {REAL})")
    parser.add_argument("--out", type=Path, default=Path("out/exit_runs"))
    args = parser.parse_args()
    sets = [s.resolve() for s in args.dataset or [REAL / name for name in REAL_SETS]]
    missing = [str(s) for s in sets if not (s / "map.txt").is_file()]
    if missing:
        print(f"exit_runs: expected reloc datasets, not found: {missing}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    work = args.out.resolve()
    tallies = {name: Tally() for name in args.command or sorted(COMMANDS)}
    for k in range(args.runs):   # interleaved, so machine load hits every command alike
        for name, tally in tallies.items():
            run = COMMANDS[name](k, sets, work)
            tally.runs.append(run)
            print(f"{name} run {k + 1}: exit {run.code} in {run.seconds:.0f} s"
                  f"{' ' + str(run.marks) if run.marks else ''}", flush=True)
            if run.code != 0 or run.marks:
                (work / f"{name}-{k}.stderr").write_text(run.stderr)
        write_outputs(work, tallies)   # after every round: a stopped run keeps its table
    print((work / "table.md").read_text(), end="")
    return 0 if all(r.code == 0 and not r.marks for t in tallies.values() for r in t.runs) else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
