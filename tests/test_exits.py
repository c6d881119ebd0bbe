"""No command exits abnormally: every helper thread is stopped and joined before the
interpreter finalizes (a daemon thread of ours returning from OpenCV or Zenoh then is ended
with ``pthread_exit``, whose unwinding through a ``catch (...)`` aborts the process: "FATAL:
exception not rethrown", exit 134). The commands run as subprocesses, as a user runs them."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from service_support import ROOT, ServiceProcess, free_port, write_config

MINI = Path(__file__).parent / "data" / "tum_fr1_rpy_mini"

#: What an abnormal end leaves on stderr (glibc's and the C++ runtime's abort messages, an
#: uncaught Python exception).
ABNORMAL = ("FATAL", "Abort", "terminate called", "Traceback", "Fatal Python error")

#: Registered before anything of reloc is imported, so it runs after every exit handler of
#: reloc (they run last registered first): the threads of ours still alive at that point,
#: just before the interpreter finalizes, written to stderr.
THREADS_AT_EXIT = '''
import atexit, os, threading

def _threads_at_exit(write=os.write):
    names = sorted(t.name for t in threading.enumerate()
                   if t.is_alive() and t.name.startswith("reloc-"))
    write(2, ("threads at exit: " + ",".join(names) + "\\n").encode())

atexit.register(_threads_at_exit)
'''


def run_python(code: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", THREADS_AT_EXIT + textwrap.dedent(code)],
                          cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def run_reloc(*argv: str, timeout: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "reloc_service.cli.main", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def assert_clean_exit(proc: subprocess.CompletedProcess[str] | tuple[int, str]) -> None:
    code, stderr = (proc.returncode, proc.stderr) if not isinstance(proc, tuple) else proc
    assert code == 0, f"exit {code}: {stderr[-3000:]}"
    found = [word for word in ABNORMAL if word in stderr]
    assert not found, f"{found} on stderr: {stderr[-3000:]}"


def threads_at_exit(stderr: str) -> list[str]:
    lines = [line for line in stderr.splitlines() if line.startswith("threads at exit:")]
    assert lines, f"the exit handler did not run: {stderr[-2000:]}"
    return [name for name in lines[-1].split(":", 1)[1].strip().split(",") if name]


def test_a_step_started_ahead_inside_opencv_ends_before_the_interpreter_finalizes():
    # A fallback chain's next step's features, extracted ahead for the last query and not
    # needed (the current step verified): still inside OpenCV when the program ends.
    proc = run_python('''
        import time
        import cv2
        import numpy as np
        from reloc_service.algorithms.relocalizers import overlap

        overlap.idle_core = lambda: True    # a core to spare, whatever else runs
        image = np.zeros((480, 640), np.uint8)

        def extract_for(seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                cv2.GaussianBlur(image, (0, 0), 5)
            return "done"

        ahead = overlap.run_ahead(lambda: extract_for(1.0))
        assert ahead is not None and not ahead.done
        print("the program ends with the step under way")
    ''')
    assert_clean_exit(proc)
    assert threads_at_exit(proc.stderr) == []


def test_an_outbox_left_open_is_closed_before_the_interpreter_finalizes():
    proc = run_python(f'''
        from reloc_client.client import RelocClient
        from reloc_client.outbox import Outbox

        client = RelocClient("tcp/127.0.0.1:{free_port()}", map="lab", mode="peer")
        outbox = Outbox(client, ack_timeout=1.0)
        print("the program ends without closing its outbox")
    ''')
    assert_clean_exit(proc)
    assert threads_at_exit(proc.stderr) == []


@pytest.mark.slow
def test_reloc_serve_stops_on_sigterm_with_no_thread_of_ours_left(tmp_path):
    port = free_port()
    service = ServiceProcess(write_config(tmp_path, port), port, tmp_path / "serve.log")
    try:
        service.proc.send_signal(signal.SIGTERM)
        code = service.proc.wait(60)
    finally:
        service.close()
    log = (tmp_path / "serve.log").read_text()
    assert_clean_exit((code, log))
    # serve leaves with os._exit, naming them, when threads of ours are still running
    assert "exiting without waiting for" not in log


@pytest.mark.slow
def test_reloc_eval_with_the_default_chain_exits_cleanly(tmp_path):
    out = tmp_path / "eval.json"
    proc = run_reloc("eval", str(MINI), "--no-progress", "--json", str(out), timeout=600)
    assert_clean_exit(proc)
    assert out.is_file() and "sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p" in proc.stdout


@pytest.mark.slow
def test_reloc_demo_exits_cleanly():
    proc = run_reloc("demo", timeout=900)
    assert_clean_exit(proc)


@pytest.mark.slow
def test_reloc_bench_quick_exits_cleanly(tmp_path):
    out = tmp_path / "bench.json"
    proc = run_reloc("bench", "--quick", "--json", str(out), "--workdir", str(tmp_path / "work"),
                     timeout=3600)
    assert_clean_exit(proc)
    assert out.is_file()
