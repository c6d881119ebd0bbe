"""What a served fleet of maps holds in memory, seen from outside the service: the resident
memory of its process tree sampled over a run (:class:`RssSampler`), and the residency
manager's own accounting as its log lines state it (:class:`ResidencyLog`)."""

from __future__ import annotations

import contextlib
import re
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ...service.memory import descendants, rss_bytes, total_rss_bytes, trim_now

T = TypeVar("T")


def tree_rss_mb(pid: int) -> float:
    """Resident memory (MiB) of process ``pid`` and its descendants (worker processes,
    their forkserver): the sum of their ``VmRSS``; 0 once they are gone."""
    return total_rss_bytes([pid, *descendants(pid)]) / (1024 * 1024)


def peak_during(work: Callable[[], T], period_s: float = 0.002) -> tuple[int, int, T]:
    """(resident bytes of this process before, their peak while ``work()`` ran, sampled
    every ``period_s`` on a thread, and its result); the heap's free pages are given back
    first, so that what ``work`` reuses of them is not missed."""
    trim_now()
    before = rss_bytes()
    peak = [before]
    done = threading.Event()

    def sample() -> None:
        while not done.wait(period_s):
            peak[0] = max(peak[0], rss_bytes())

    sampler = threading.Thread(target=sample, name="rss-peak", daemon=True)
    sampler.start()
    try:
        result = work()
    finally:
        done.set()
        sampler.join()
    return before, max(peak[0], rss_bytes()), result


@dataclass(eq=False)
class RssSampler:
    """:func:`tree_rss_mb` of ``pid`` every ``period_s`` on a thread while :meth:`running`."""

    pid: int
    period_s: float
    samples: list[tuple[float, float]] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)

    def sample(self) -> float:
        """One sample now (kept with the others): MiB."""
        value = tree_rss_mb(self.pid)
        self.samples.append((time.monotonic(), value))
        return value

    @contextlib.contextmanager
    def running(self) -> Iterator[RssSampler]:
        thread = threading.Thread(target=self._loop, name="rss-sampler", daemon=True)
        thread.start()
        try:
            yield self
        finally:
            self._stop.set()
            thread.join()

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()

    def summary(self) -> dict[str, Any]:
        values = [v for _, v in self.samples if v > 0]
        if not values:
            return {"samples": 0, "max_mb": None, "p50_mb": None, "last_mb": None}
        return {"samples": len(values), "max_mb": max(values),
                "p50_mb": float(np.median(values)), "last_mb": values[-1]}


#: The residency manager's lines (service/residency.py): a map loaded, a map closed, each
#: with the counted megabytes resident after it and the budget.
_LOADED = re.compile(r"map (\S+): loaded on demand in ([\d.]+) s \(([\d.]+) MB resident of "
                     r"([\d.]+) MB\)")
_CLOSED = re.compile(r"map (\S+): closed \(idle; ([\d.]+) MB resident of ([\d.]+) MB\)")


@dataclass
class ResidencyLog:
    """What the residency manager logged: each cold load's seconds and the counted MB
    resident after each load and each close."""

    load_s: list[float] = field(default_factory=list)
    after_load_mb: list[float] = field(default_factory=list)
    after_close_mb: list[float] = field(default_factory=list)
    budget_mb: float | None = None

    @classmethod
    def read(cls, log: Path) -> ResidencyLog:
        out = cls()
        for line in log.read_text(errors="replace").splitlines():
            if m := _LOADED.search(line):
                out.load_s.append(float(m[2]))
                out.after_load_mb.append(float(m[3]))
                out.budget_mb = float(m[4])
            elif m := _CLOSED.search(line):
                out.after_close_mb.append(float(m[2]))
                out.budget_mb = float(m[3])
        return out

    @property
    def loads(self) -> int:
        return len(self.load_s)

    def summary(self) -> dict[str, Any]:
        """Loads and closes, the load seconds' p50/max, and the largest counted MB resident
        right after a load (before the evictor closes the least recently used: the budget
        may be exceeded by one map for that moment) and after a close."""
        def top(values: list[float]) -> float | None:
            return max(values) if values else None

        return {"loads": self.loads, "closes": len(self.after_close_mb),
                "load_p50_s": float(np.median(self.load_s)) if self.load_s else None,
                "load_max_s": top(self.load_s), "max_after_load_mb": top(self.after_load_mb),
                "max_after_close_mb": top(self.after_close_mb), "budget_mb": self.budget_mb}
