"""What a benchmark run ran on: CPU, cores, library versions (from ``reloc eval``), the load of
the machine and the thread settings, and the resident memory of this process."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path
from typing import Any

from ..eval.evaluate import machine_info

#: Extra distributions a benchmark depends on (``machine_info`` lists the core ones).
_BENCH_LIBRARIES = ("matplotlib",)


def load_average() -> list[float] | None:
    """The 1, 5 and 15 minute load averages (None where the OS does not tell)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def machine_record() -> dict[str, Any]:
    """``reloc eval``'s machine record (CPU model, cores, platform, Python, library versions)
    plus the load average, the OpenCV thread count and the BLAS thread setting."""
    from importlib import metadata

    import cv2

    record = machine_info()
    for name in _BENCH_LIBRARIES:
        try:
            record["libraries"][name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            record["libraries"][name] = None
    record["load_average_at_start"] = load_average()
    record["opencv_threads"] = cv2.getNumThreads()
    record["blas_threads"] = blas_threads_record()
    record["memory_total_mb"] = _meminfo_mb("MemTotal")
    record["started_unix"] = round(time.time(), 1)
    return record


def code_record(repo: Path | None = None) -> dict[str, Any]:
    """Which code ran: the git commit of the repository holding this package and whether its
    tracked files had changes (both None outside a git checkout)."""
    repo = repo or Path(__file__).resolve().parents[3]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(repo), *args], capture_output=True,
                                  text=True, timeout=10, check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def blas_threads_record() -> dict[str, int]:
    """Threads of each BLAS loaded in this process (file name -> threads), as they are now."""
    from threadpoolctl import threadpool_info

    return {Path(lib["filepath"]).name: int(lib["num_threads"])
            for lib in threadpool_info() if lib["user_api"] == "blas"}


def rss_mb(field: str = "VmRSS", pid: int | None = None) -> float | None:
    """The resident memory (``VmRSS``) or its peak (``VmHWM``) in MiB of process ``pid``
    (this process when None), from ``/proc/PID/status``; None where the process is gone or
    there is no such file."""
    try:
        with open(f"/proc/{'self' if pid is None else pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return None


def _meminfo_mb(field: str) -> float | None:
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return None
