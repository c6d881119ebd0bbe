"""The compiled kernels are loaded before the first query: by a worker process at its start
(``worker_main``) and, for a service answering on threads, on a thread from its start."""

from __future__ import annotations

import subprocess
import sys
import textwrap

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
