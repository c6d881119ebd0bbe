"""The compiled kernels (numba, the [jit] extra) loaded before the first query rather than
within its answer time: numba's import and the load of about 16 kernels from its on-disk
cache take 1.5-2 s of a fresh process, which the first query would otherwise pay. A worker
process loads them when it starts; a service answering on threads, on a thread of its own
from its start (while it opens Zenoh and loads its first map).

What the warm-up adds to the process's resident memory (numba, LLVM and the kernels: its
*growth*) counts in the service's memory budget (:mod:`.residency`) from the start, before
it is measured, so that no cold load waits for the warm-up's end: its last clean measure,
recorded in the storage (:func:`recorded_growth`), else :data:`GROWTH_RESERVE_BYTES`.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..algorithms.pose import kernels as pose_kernels
from ..core import hamming
from ..core.background import start_background
from ..core.fileio import atomic_write
from ..core.frame import area_downscale
from ..core.numeric import first_occurrences

log = logging.getLogger(__name__)

#: The name of the thread :func:`warm_in_background` starts.
THREAD_NAME = "warm-kernels"

#: What the warm-up adds to a fresh service process's resident memory when no measure is
#: recorded: 105.8 MB measured (three fresh processes, the service and Zenoh imported,
#: heap trimmed before and after, the kernels loaded from numba's on-disk cache), rounded
#: up to the next MB. A first start that compiles them grows by about 204 MB (measured
#: once): that start's estimate is short until its growth is measured cleanly.
GROWTH_RESERVE_BYTES = 106 * 1024 * 1024

#: The file in a service's storage that records the warm-up's last clean measure.
GROWTH_FILE = "warm_up.json"

_warmed = threading.Event()   # warm_kernels ran in this process (it adds nothing more)


def warm_kernels() -> None:
    """Load (or compile) every kernel the default method's queries call, on a few values;
    nothing where numba is not installed."""
    orb = np.zeros((2, 32), np.uint8)   # ORB's 256-bit descriptors, as queries match them
    hamming.knn2(orb, orb)
    pose_kernels.warm_up()
    first_occurrences(np.array([2, 1, 2], np.int64))   # pooling several keyframes' landmarks
    area_downscale(np.zeros((32, 32), np.uint8), 2, 2)
    _warmed.set()


def expected_growth(storage: Path | None) -> int:
    """What this process's warm-up will add to its resident memory (bytes): 0 once it ran
    here or without numba, else the measure recorded in ``storage``, else
    :data:`GROWTH_RESERVE_BYTES`."""
    if _warmed.is_set() or importlib.util.find_spec("numba") is None:
        return 0
    recorded = None if storage is None else recorded_growth(storage)
    return GROWTH_RESERVE_BYTES if recorded is None else recorded


def recorded_growth(storage: Path) -> int | None:
    """The warm-up's growth recorded in ``storage`` (bytes), None when none (or unreadable)."""
    try:
        value = json.loads((storage / GROWTH_FILE).read_text())["growth_bytes"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return int(value) if isinstance(value, int) and value >= 0 else None


def record_growth(storage: Path, growth: int) -> None:
    """Record the warm-up's ``growth`` (bytes, measured with no map resident) in
    ``storage`` for the next start; a failure to write is logged only."""
    try:
        atomic_write(storage / GROWTH_FILE,
                     json.dumps({"growth_bytes": max(0, int(growth))}).encode(), fsync=False)
    except OSError as exc:
        log.warning("the warm-up's memory growth not recorded in %s: %s", storage, exc)


def warm_in_background(done: Callable[[], None] | None = None) -> threading.Thread:
    """Run :func:`warm_kernels` on a background thread (:mod:`..core.background`: exit waits
    for it; a failure is logged: the first query loads what is missing), then ``done`` (the
    residency measures the service's baseline memory then), whether it succeeded or not."""

    def run() -> None:
        start = time.perf_counter()
        try:
            warm_kernels()
            log.debug("compiled kernels loaded in %.2f s", time.perf_counter() - start)
        except Exception as exc:
            log.warning("loading the compiled kernels ahead of the first query failed: %s", exc)
        finally:
            if done is not None:
                done()

    return start_background(run, THREAD_NAME)   # exit waits: no compile under teardown
