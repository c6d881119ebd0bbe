"""What a benchmark run ran on: CPU, cores, library versions (from ``reloc eval``), the load of
the machine and the thread settings, and the resident memory of this process."""

from __future__ import annotations

import os
import time
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
    record["blas_threads"] = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    record["memory_total_mb"] = _meminfo_mb("MemTotal")
    record["started_unix"] = round(time.time(), 1)
    return record


def rss_mb(field: str = "VmRSS") -> float | None:
    """This process's resident memory (``VmRSS``) or its peak (``VmHWM``) in MiB, from
    ``/proc/self/status``; None where there is no such file."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
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
