"""``reloc serve`` raises its soft open-file limit to what its maps need (systemd's default soft
limit is 1024 under a much higher hard limit), and warns with the numbers when even the hard
limit cannot hold ``quotas.max_maps`` maps. Real ``reloc serve`` processes with their limits
set before exec."""

from __future__ import annotations

import resource
import signal
import subprocess
import sys
import time

import pytest
from service_support import free_port, write_config

from reloc_service.service import open_files


def _serve_with_limit(tmp_path, soft: int, hard: int, **quotas) -> tuple[int, str]:
    """Start ``reloc serve`` with RLIMIT_NOFILE (soft, hard); once it logs that it serves,
    read the soft limit it runs with (/proc), stop it; (its soft limit, its log)."""
    config = write_config(tmp_path, free_port())
    if quotas:
        config.write_text(config.read_text() + "[quotas]\n" + "".join(
            f"{k} = {v}\n" for k, v in quotas.items()))
    log = tmp_path / "serve.log"

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))

    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                                 "--config", str(config)], stdout=out,
                                stderr=subprocess.STDOUT, preexec_fn=limit)
    try:
        deadline = time.monotonic() + 60
        while "open files" not in log.read_text() and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()
            time.sleep(0.1)
        limits = open(f"/proc/{proc.pid}/limits").read()
        line = next(x for x in limits.splitlines() if x.startswith("Max open files"))
        running_soft = int(line.split()[3])
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0, log.read_text()
    return running_soft, log.read_text()


@pytest.fixture(scope="module")
def low_limits(tmp_path_factory) -> tuple[int, str]:
    """One ``reloc serve`` started with a soft limit of 256 under a hard limit of 512 (below
    WANTED, so the hard one is the target) and quotas.max_maps = 1000 (more than 512 files
    hold): both tests below read its soft limit and its log (a process start costs seconds
    on a loaded machine)."""
    return _serve_with_limit(tmp_path_factory.mktemp("limits"), 256, 512, max_maps=1000)


def test_serve_raises_a_low_soft_limit_to_the_hard_one(low_limits):
    soft, text = low_limits
    assert soft == 512, text
    assert "soft limit raised from 256 to 512" in text


def test_serve_warns_when_the_hard_limit_cannot_hold_max_maps(low_limits):
    soft, text = low_limits
    assert soft == 512
    needed = open_files.needed_for(1000)
    assert f"the limit 512 cannot hold quotas.max_maps = 1000 maps (about {needed}" in text


def test_what_a_map_needs_is_counted_per_map():
    assert open_files.needed_for(380) <= 1024 < open_files.needed_for(400)
