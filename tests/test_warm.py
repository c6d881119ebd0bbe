"""The compiled kernels are loaded before the first query: by a worker process at its start
(``worker_main``) and, for a service answering on threads, on a thread from its start; what
the warm-up adds to the memory a budget counts is estimated at start, measured at its end
with no map resident, and recorded for the next start."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from service_support import ROOT

pytest.importorskip("numba")

#: A fresh interpreter (the kernels load once per process): a thread-mode service started
#: with no map and no query; prints which kernels hold a loaded signature.
SCRIPT = textwrap.dedent("""
    import threading
    from service_support import free_port, service_conf
    from reloc_service.algorithms.pose import kernels
    from reloc_service.core import hamming
    from reloc_service.service.app import Service
    from reloc_service.service.warm import THREAD_NAME

    conf = service_conf(free_port(), worker_mode="thread")
    with Service(conf) as service:
        for thread in threading.enumerate():
            if thread.name == THREAD_NAME:
                thread.join(120)
        k = kernels.compiled()
        print(bool(hamming.compiled_knn2().signatures), bool(k.project.signatures),
              bool(k.fit.signatures))
""")


@pytest.mark.slow   # a fresh interpreter: its imports take seconds
def test_a_thread_mode_service_loads_its_kernels_before_any_query() -> None:
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                         cwd=ROOT / "tests", timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["True", "True", "True"]


#: A fresh interpreter: a thread-mode service with a memory budget over an empty storage
#: (argv[1]); prints the warm-up's estimate at declaration, then, once the warm-up ended
#: with no map resident, the baseline it counts, the declared memory and the growth recorded.
BUDGET_SCRIPT = textwrap.dedent("""
    import sys, threading
    from pathlib import Path
    from service_support import free_port, service_conf
    from reloc_service.service.app import Service
    from reloc_service.service.warm import recorded_growth

    storage = Path(sys.argv[1])
    conf = service_conf(free_port(), storage, worker_mode="thread", max_resident_mb=1e6)
    with Service(conf) as service:
        residency = service.registry.residency
        estimate = residency.growth_estimate
        assert residency.baseline_settled.wait(300)
        print(estimate, residency.baseline_service, residency.declared_rss,
              recorded_growth(storage))
""")


def _budget_run(storage: Path) -> list[int]:
    out = subprocess.run([sys.executable, "-c", BUDGET_SCRIPT, str(storage)],
                         capture_output=True, text=True, cwd=ROOT / "tests", timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return [int(v) for v in out.stdout.split()]


@pytest.mark.slow   # two fresh interpreters
def test_the_warm_up_growth_is_estimated_then_measured_and_recorded(tmp_path: Path) -> None:
    from reloc_service.service.warm import GROWTH_RESERVE_BYTES

    storage = tmp_path / "storage"
    storage.mkdir()
    estimate, baseline, declared, recorded = _budget_run(storage)
    assert estimate == GROWTH_RESERVE_BYTES   # nothing recorded yet: the measured reserve
    # with no map resident at its end, the warm-up is measured: the baseline is that measure
    assert recorded == baseline - declared > 0
    estimate2, baseline2, declared2, recorded2 = _budget_run(storage)
    assert estimate2 == recorded   # the next start counts the recorded growth from the start
    assert recorded2 == baseline2 - declared2 > 0
