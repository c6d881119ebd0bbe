"""The ``tools`` extra: ``pip install reloc`` alone serves (no scikit-image, no matplotlib), the
tool subcommands then say which extra they need, and ``reloc[tools]`` brings them back."""

from __future__ import annotations

import importlib.metadata
import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from service_support import endpoint, free_port, stop_process, wait_until

from reloc_service.cli.tools_extra import TOOL_COMMANDS, TOOLS_EXTRA_HINT, TOOLS_EXTRA_MODULES

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
#: Each tool subcommand with arguments it would accept when the extra is installed.
TOOL_ARGV = {"synth": ["--list"], "dataset": ["check", "DS"], "eval": ["--list-methods"],
             "bench": ["--quick"], "demo": []}


def _distributions(requirements: list[str]) -> set[str]:
    """Distribution names of requirement strings (``"scikit-image>=0.22"`` -> scikit-image)."""
    return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower() for r in requirements}


def test_the_tools_extra_is_what_the_cli_checks_for():
    """pyproject's [tools] extra and the CLI's TOOLS_EXTRA_MODULES name the same packages."""
    extras = PYPROJECT["optional-dependencies"]
    installed = importlib.metadata.packages_distributions()
    checked = {d.lower() for m in TOOLS_EXTRA_MODULES for d in installed[m]}
    assert _distributions(extras["tools"]) == checked
    assert not checked & _distributions(PYPROJECT["dependencies"]), "a tool dep is in the core"
    assert _distributions(extras["tools"]) | _distributions(extras["ros2"]) <= _distributions(
        extras["dev"]), "[dev] must hold everything the tests import"
    assert set(TOOL_ARGV) == TOOL_COMMANDS


def _reloc_without_tools_extra(argv: list[str]) -> subprocess.CompletedProcess:
    """``reloc ARGV`` in a fresh interpreter where the extra's modules cannot be imported
    (``sys.modules[name] = None`` is how Python marks a module as absent)."""
    code = (f"import sys\nfor m in {TOOLS_EXTRA_MODULES!r}: sys.modules[m] = None\n"
            f"from reloc_service.cli.main import main\nsys.exit(main({argv!r}))")
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


@pytest.mark.parametrize("command", sorted(TOOL_COMMANDS))
def test_a_tool_without_the_extra_says_which_extra_to_install(command):
    proc = _reloc_without_tools_extra([command, *TOOL_ARGV[command]])
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == (f"reloc {command} {TOOLS_EXTRA_HINT} (not installed: "
                                   f"{', '.join(TOOLS_EXTRA_MODULES)})")


def test_serve_and_map_check_do_not_need_the_extra():
    for argv in (["serve", "--help"], ["map", "check", "--help"], ["--help"]):
        proc = _reloc_without_tools_extra(argv)
        assert proc.returncode == 0 and "usage: reloc" in proc.stdout, (argv, proc.stderr)


# -- a real installation without extras ------------------------------------------------------

def _copy_source(dest: Path) -> None:
    """What the wheel is built from, copied so the build leaves nothing in the checkout."""
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dest / name)
    for name in ("reloc_service", "clients"):
        shutil.copytree(ROOT / name, dest / name, ignore=ignore)


def _run(venv: Path, *argv: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    """``venv/bin/ARGV[0] ARGV[1:]`` with no trace of this checkout on its import path."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run([str(venv / "bin" / argv[0]), *argv[1:]], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def _serve_config(tmp: Path, port: int) -> Path:
    path = tmp / "serve.toml"
    path.write_text("\n".join([
        "[zenoh]", 'mode = "peer"', f'listen = ["{endpoint(port)}"]',
        "multicast_scouting = false", "[service]", 'instance = "core-only"',
        f'storage = "{tmp / "storage"}"', "[maps.lab]", ""]))
    return path


def _check_serve_answers(venv: Path, tmp: Path) -> None:
    """``reloc serve`` from ``venv`` starts and answers ``reloc-client`` status and maps."""
    port = free_port()
    log = open(tmp / "serve.log", "wb")
    server = subprocess.Popen([str(venv / "bin" / "reloc"), "serve", "--config",
                               str(_serve_config(tmp, port))], cwd=tmp, stdout=log, stderr=log)
    client = ("reloc-client", "--connect", endpoint(port), "--timeout", "2")
    try:
        status = wait_until(lambda: _status(venv, client, tmp, server), timeout=90, interval=0.5)
        assert status["map"] == "lab" and status["instance"] == "core-only"
        maps = _run(venv, *client, "maps", cwd=tmp)
        assert maps.returncode == 0, maps.stderr
        assert {"instance": "core-only", "map": "lab"} in json.loads(maps.stdout)
    finally:
        stop_process(server)
        log.close()


def _status(venv: Path, client: tuple[str, ...], tmp: Path, server: subprocess.Popen):
    if server.poll() is not None:
        raise AssertionError(f"reloc serve exited with {server.returncode}: "
                             f"{(tmp / 'serve.log').read_text()[-2000:]}")
    proc = _run(venv, *client, "--map", "lab", "status", cwd=tmp)
    return json.loads(proc.stdout) if proc.returncode == 0 else None


@pytest.mark.slow
def test_pip_install_without_extras_serves_and_tools_need_the_extra(tmp_path):
    """``pip install .`` into a venv of its own (no system site-packages; pip takes the wheels
    from its local cache): the service and the client work, scikit-image and matplotlib are
    absent, each tool says which extra it needs; ``pip install .[tools]`` restores the tools."""
    src, venv, run = tmp_path / "src", tmp_path / "venv", tmp_path / "run"
    src.mkdir()
    run.mkdir()
    _copy_source(src)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    installed = _run(venv, "python", "-m", "pip", "install", "-q", str(src), cwd=run, timeout=900)
    assert installed.returncode == 0, installed.stderr[-3000:]

    for module in TOOLS_EXTRA_MODULES:
        assert _run(venv, "python", "-c", f"import {module}", cwd=run).returncode != 0, module
    helped = _run(venv, "reloc", "--help", cwd=run)
    assert helped.returncode == 0 and "serve" in helped.stdout, helped.stderr
    for command in sorted(TOOL_COMMANDS):
        refused = _run(venv, "reloc", command, *TOOL_ARGV[command], cwd=run)
        assert refused.returncode == 2, (command, refused.stderr)
        assert TOOLS_EXTRA_HINT in refused.stderr and "Traceback" not in refused.stderr
    _check_serve_answers(venv, run)

    tools = _run(venv, "python", "-m", "pip", "install", "-q", f"{src}[tools]", cwd=run,
                 timeout=900)
    assert tools.returncode == 0, tools.stderr[-3000:]
    listed = _run(venv, "reloc", "synth", "--list", cwd=run)
    assert listed.returncode == 0 and "room-hard" in listed.stdout, listed.stderr


def test_the_service_configuration_needs_no_ros2_extra():
    """``reloc serve`` reads [ros2] (and [ros2.px4]) on every install: loading the
    configuration imports neither rosbags nor xxhash (the ``ros2`` extra), only enabling the
    bridge does. The slow plain-install test shows the same on a real install."""
    import subprocess
    import sys

    code = ("import sys; import reloc_service.service.config, reloc_service.service.app; "
            "extra = sorted(m for m in ('rosbags', 'xxhash') if m in sys.modules); "
            "print(extra); sys.exit(1 if extra else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
