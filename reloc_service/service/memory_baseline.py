"""The processes' own memory, counted against a service's memory budget
(``[service] max_resident_mb``) before its maps (:class:`~.residency.Residency`).

The processes' own memory counts too: the budget is the whole service's (its process and its
worker processes). The service's resident memory with no map (``VmRSS``: interpreter, OpenCV,
Zenoh, and the compiled kernels its warm-up loads: numba and LLVM, about 106 MB) is its
*baseline*: measured when the maps are declared, before the warm-up starts, plus what the
warm-up will add (:func:`.warm.expected_growth`: its last clean measure, else a measured
reserve), so no cold load waits for the warm-up. When the warm-up ends with no map resident
or loading, the baseline is measured again and that measure replaces the estimate (and the
growth is recorded for the next start); else the estimate stays. With ``worker_mode =
"process"`` the forkserver's and the workers' count too, measured once each worker has warmed
up and before it holds any replica. The maps get ``max_resident_mb`` minus the baseline. A
budget the baseline at declaration fills refuses to start (ConfigError naming both); one that
only the warmed-up baseline fills is logged as an error, and every idle map is closed.

The queries count too: each worker (thread or process) holds a query's working memory while
it answers one (the decoded image, its features and scale space, the candidates' matches),
freed when it ends, so the baseline keeps :func:`query_working_bytes` of the largest image a
query may carry (``limits.max_image_pixels``) per worker.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any, Protocol

from ..core.errors import ConfigError
from .memory import rss_bytes, total_rss_bytes, trim_now
from .warm import record_growth

log = logging.getLogger(__name__)

MB = 1024 * 1024

#: What a query holds in memory while it is answered, above what the process holds between
#: queries, grows with its pixels (SIFT's scale space, on an image doubled in size): an image
#: of no map's scene, which the default method runs through all its steps (full-size SIFT
#: included) and refuses, held 77.0 MB at 640x480, 150.8 MB at 960x720 and 272.4 MB at
#: 1280x960 (python scripts/query_working_memory.py T --scales 1 1.5 2, on the fleet
#: template; 4.5-5.1 MB when the ORB step answers, 19.6-21.0 MB when the half-size SIFT step
#: does, at 640x480). A fixed part and a part per pixel, the line through the two ends
#: rounded up, bound all three: 77.6, 159.7 and 274.5 MB.
QUERY_WORKING_FIXED_BYTES = 12 * MB
QUERY_WORKING_BYTES_PER_PIXEL = 224


def query_working_bytes(max_image_pixels: int) -> int:
    """What one query of at most ``max_image_pixels`` pixels may hold while it is answered
    (bytes)."""
    if max_image_pixels < 1:
        raise ValueError(f"expected max_image_pixels >= 1, got {max_image_pixels}")
    return QUERY_WORKING_FIXED_BYTES + QUERY_WORKING_BYTES_PER_PIXEL * max_image_pixels


class ServedMaps(Protocol):
    """What the baseline reads of the service's map registry: whether a map is resident,
    and where the storage records the warm-up's growth."""

    storage: Path | None
    maps: dict[str, Any]


class ProcessBaseline:
    """The budget and the processes' baseline of a :class:`~.residency.Residency` (its base:
    the attributes are set by its constructor, which documents them)."""

    registry: ServedMaps
    total_budget: int
    baseline_service: int
    baseline_workers: int
    baseline_queries: int
    budget: int
    declared_rss: int
    growth_estimate: int
    baseline_settled: threading.Event
    _declared: bool
    _warmed: bool
    _lock: threading.Lock
    _loading: set[str]
    _wake: threading.Event

    def resident_bytes(self) -> int:
        """What the resident maps count (bytes; :class:`~.residency.Residency`'s)."""
        raise NotImplementedError

    @property
    def baseline(self) -> int:
        """The processes' own resident memory and their queries' working memory, counted
        against the budget (bytes)."""
        return self.baseline_service + self.baseline_workers + self.baseline_queries

    def count_service_baseline(self, warm_up_growth: int = 0) -> None:
        """Measure this process's resident memory (no map resident yet) and count it, with
        ``warm_up_growth`` (bytes) if its warm-up has not ended: what that will add
        (:func:`.warm.expected_growth`). ConfigError naming both numbers when that alone
        fills the budget."""
        with self._lock:
            self.declared_rss = _settled_rss()
            self.growth_estimate = 0 if self._warmed else max(0, warm_up_growth)
            self.baseline_service = self.declared_rss + self.growth_estimate
            self._declared = True
            if self._warmed:
                self.baseline_settled.set()
        if self.baseline >= self.total_budget:
            raise ConfigError(
                f"service.max_resident_mb = {self.total_budget / MB:.0f} MB: expected more "
                f"than the service's own resident memory with no map and its workers' "
                f"queries, {self.baseline / MB:.0f} MB (the budget counts the whole service: "
                f"{self.baseline_queries / MB:.0f} MB of it for the queries, each of up to "
                f"limits.max_image_pixels)")
        self._set_maps_budget()

    def settle_service_baseline(self) -> None:
        """The service's warm-up has ended. With no map resident or loading, its resident
        memory is measured again and replaces the estimate (the growth, when a fresh
        warm-up's, is recorded in the storage for the next start: :func:`.warm.record_growth`);
        with one, the estimate stays (the measure would count the map). Past the budget the
        service runs on (it is serving already): the error is logged."""
        growth = None
        with self._lock:
            self._warmed = True
            if self._declared and not self.registry.maps and not self._loading:
                self.baseline_service = _settled_rss()
                growth = self.baseline_service - self.declared_rss
            elif self._declared:
                log.info("the warm-up ended with a map resident: its memory is counted as "
                         "estimated, %.1f MB", self.growth_estimate / MB)
        if growth is not None and self.growth_estimate and self.registry.storage is not None:
            record_growth(self.registry.storage, growth)
        if self._declared:
            self.baseline_settled.set()
        if self.baseline >= self.total_budget:
            log.error("service.max_resident_mb = %.0f MB is filled by the service's own "
                      "resident memory with no map after its warm-up, %.0f MB: every idle map "
                      "is closed", self.total_budget / MB, self.baseline / MB)
        self._set_maps_budget()
        self._wake.set()

    def count_workers_baseline(self, pids: list[int]) -> None:
        """Measure the worker processes' (and their forkserver's) resident memory ``pids``
        as they start, and count it. Past the budget the service runs on (it is already
        serving): every idle map is closed, and the error is logged."""
        self.baseline_workers = total_rss_bytes(pids)
        if self.baseline >= self.total_budget:
            log.error("service.max_resident_mb = %.0f MB is filled by the processes' own "
                      "resident memory with no map, %.0f MB (service %.0f MB, %d worker "
                      "processes %.0f MB): every idle map is closed", self.total_budget / MB,
                      self.baseline / MB, self.baseline_service / MB, len(pids),
                      self.baseline_workers / MB)
        self._set_maps_budget()
        self._wake.set()

    def set_total_budget(self, budget_mb: float) -> None:
        """Make the whole service's budget ``budget_mb``, as ``service.max_resident_mb``
        does at start: the maps get it minus the measured baseline; idle maps past it close."""
        if not budget_mb > 0:
            raise ValueError(f"expected a budget > 0 MB, got {budget_mb}")
        self.total_budget = int(budget_mb * MB)
        self._set_maps_budget()
        self._wake.set()

    def _set_maps_budget(self) -> None:
        # at least one byte: a budget of 0 would mean "no budget" to the checks below
        self.budget = max(1, self.total_budget - self.baseline)
        log.info("memory budget %.1f MB: processes' baseline %.1f MB (service %.1f MB, workers "
                 "%.1f MB, queries %.1f MB), maps %.1f MB", self.total_budget / MB,
                 self.baseline / MB, self.baseline_service / MB, self.baseline_workers / MB,
                 self.baseline_queries / MB, self.budget / MB)

    def memory_counters(self) -> dict[str, int]:
        """The budget, the processes' baseline and the maps' count and share, in bytes, as
        every map's status counters carry them:
        ``memory_budget_bytes`` (``max_resident_mb``), ``memory_baseline_bytes`` (the
        processes' own, with its ``_service``, ``_workers`` and ``_queries`` parts),
        ``memory_maps_budget_bytes`` (the maps' share) and ``memory_maps_bytes`` (what the
        resident maps count)."""
        return {"memory_budget_bytes": self.total_budget, "memory_baseline_bytes": self.baseline,
                "memory_baseline_service_bytes": self.baseline_service,
                "memory_baseline_workers_bytes": self.baseline_workers,
                "memory_baseline_queries_bytes": self.baseline_queries,
                "memory_maps_budget_bytes": self.budget,
                "memory_maps_bytes": self.resident_bytes()}


def _settled_rss() -> int:
    """This process's resident memory once the heap's free pages are given back (what it
    holds, not what its start-up freed: the measure then varies less between starts)."""
    trim_now()
    return rss_bytes()
