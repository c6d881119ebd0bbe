"""The compiled kernels (numba, the [jit] extra) loaded before the first query rather than
within its answer time: numba's import and the load of about 16 kernels from its on-disk
cache take 1.5-2 s of a fresh process, which the first query would otherwise pay. A worker
process loads them when it starts; a service answering on threads, on a thread of its own
from its start (while it opens Zenoh and loads its first map)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from ..algorithms.pose import kernels as pose_kernels
from ..core import hamming
from ..core.background import start_background
from ..core.frame import area_downscale

log = logging.getLogger(__name__)

#: The name of the thread :func:`warm_in_background` starts.
THREAD_NAME = "warm-kernels"


def warm_kernels() -> None:
    """Load (or compile) every kernel the default method's queries call, on a few values;
    nothing where numba is not installed."""
    orb = np.zeros((2, 32), np.uint8)   # ORB's 256-bit descriptors, as queries match them
    hamming.knn2(orb, orb)
    pose_kernels.warm_up()
    area_downscale(np.zeros((32, 32), np.uint8), 2, 2)


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
