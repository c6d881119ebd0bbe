"""Work reloc leaves running in the background ends before the interpreter does: background
threads are asked to stop and waited for at exit, and a file mapping is not unmapped under
a thread still reading it while the process exits."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

from reloc_service.core.background import LOWER_PRIORITY, start_background, stop_background


def test_stop_asks_background_work_to_end_and_waits_for_it() -> None:
    cancel = threading.Event()
    finished = threading.Event()

    def work() -> None:
        cancel.wait(30.0)   # stands for units of work that check the event between them
        finished.set()

    thread = start_background(work, "test-cancellable", cancel)
    assert thread.daemon and thread.is_alive()
    assert stop_background(timeout_s=10.0) == []
    assert cancel.is_set() and finished.is_set() and not thread.is_alive()


def test_stop_names_work_that_outlives_the_wait() -> None:
    release = threading.Event()
    thread = start_background(lambda: release.wait(30.0), "test-stubborn")   # no cancel
    try:
        assert stop_background(timeout_s=0.2) == ["test-stubborn"]
    finally:
        release.set()
        thread.join(10.0)
    assert stop_background(timeout_s=1.0) == []


def test_a_thread_reading_a_mapped_file_does_not_crash_the_exit(tmp_path: Path) -> None:
    """A daemon thread reads a mapped file without pause while the main thread returns: the
    process exits cleanly (the mapping is not unmapped by the exit's finalizers under it)."""
    data = tmp_path / "data.bin"
    data.write_bytes(bytes(range(256)) * 4096)
    script = textwrap.dedent(f"""
        import threading
        from reloc_service.core.file_mapping import map_file
        with open({str(data)!r}, "rb") as fh:
            mapped = map_file(fh, {data.stat().st_size})
        array = mapped.array
        reading = threading.Event()

        def read_forever():
            while True:
                int(array.sum())
                reading.set()

        threading.Thread(target=read_forever, daemon=True).start()
        reading.wait(30.0)
        del mapped
        print("main done")
    """)
    for _ in range(3):
        run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                             timeout=120)
        assert (run.returncode, run.stdout.strip()) == (0, "main done"), run.stderr[-2000:]


def test_work_that_yields_to_queries_runs_at_a_lower_priority_than_the_rest() -> None:
    """The thread's own nice value is raised; the process's other threads keep theirs."""
    seen: dict[str, int] = {}

    def nice_of_this_thread() -> int:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    def work(key: str) -> None:
        seen[key] = nice_of_this_thread()

    ours = nice_of_this_thread()
    start_background(lambda: work("yields"), "test-yields", yield_to_queries=True).join(10)
    start_background(lambda: work("plain"), "test-plain").join(10)
    # at most 19: a process already at nice > 9 (a bench under `nice -n 10`) stops there
    assert seen == {"yields": min(19, ours + LOWER_PRIORITY), "plain": ours}
    assert nice_of_this_thread() == ours
