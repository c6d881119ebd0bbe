"""The ``reloc`` command line: instant help (no heavy imports), subcommand parsing, errors."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from reloc_service.cli import main as cli_main
from reloc_service.cli.eval import load_options
from reloc_service.cli.tools_extra import TOOL_COMMANDS
from reloc_service.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("numpy", "cv2", "scipy", "zenoh", "matplotlib", "poselib", "skimage")


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)


@pytest.mark.parametrize("argv", [["--help"], ["eval", "--help"], ["--version"]])
def test_help_imports_nothing_heavy(argv):
    code = f"""
import sys
from reloc_service.cli.main import main
try:
    main({argv!r})
except SystemExit:
    pass
heavy = sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r})
print('RESULT', ','.join(heavy), file=sys.stderr)
"""
    proc = _python(code)
    line = [x for x in proc.stderr.splitlines() if x.startswith("RESULT")][0].split(" ")
    heavy = line[1] if len(line) > 1 else ""
    assert heavy == "", f"reloc {' '.join(argv)} imported {heavy}"
    assert "usage: reloc" in proc.stdout or "reloc 0." in proc.stdout


def test_help_imports_no_subcommand_implementation():
    """The subcommand modules give their help without importing what implements them."""
    code = """
import sys
from reloc_service.cli.main import main
try:
    main(["--help"])
except SystemExit:
    pass
print("LOADED", *sorted(m for m in sys.modules if m.startswith("reloc")), file=sys.stderr)
"""
    line = [x for x in _python(code).stderr.splitlines() if x.startswith("LOADED")][0]
    loaded = line.split()[1:]
    assert loaded and all(m in ("reloc_service", "reloc_service.cli")
                          or m.startswith("reloc_service.cli.") for m in loaded), loaded


def test_every_subcommand_is_listed(capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in ("synth", "dataset", "eval", "serve", "bench", "demo", "router"):
        assert name in out


def test_version(capsys):
    with pytest.raises(SystemExit):
        cli_main.main(["--version"])
    assert capsys.readouterr().out.startswith("reloc 0.")


def test_no_command_prints_help_and_fails(capsys):
    assert cli_main.main([]) == 2
    assert "usage: reloc" in capsys.readouterr().err


def test_eval_arguments_parse():
    parser = cli_main.build_parser("eval")
    args = parser.parse_args(["eval", "DS", "--method", "gt+none", "-m", "bow+p3p,sbi+esm",
                              "--json", "o.json", "--plots", "p", "--landmarks", "depth"])
    assert args.dataset == "DS"
    assert args.method == ["gt+none", "bow+p3p,sbi+esm"]
    assert (args.json, args.plots, args.landmarks) == ("o.json", "p", "depth")
    with pytest.raises(SystemExit):
        parser.parse_args(["eval", "DS", "--landmarks", "lidar"])


def test_eval_query_camera_arguments_parse():
    parser = cli_main.build_parser("eval")
    args = parser.parse_args(["eval", "DS", "-m", "default", "--query-focal-scale", "1.05",
                              "--query-k1", "2"])
    assert (args.query_focal_scale, args.query_k1) == (1.05, 2.0)
    defaults = parser.parse_args(["eval", "DS"])
    assert (defaults.query_focal_scale, defaults.query_k1) == (1.0, None)


def test_eval_usage_errors(capsys):
    assert cli_main.main(["eval", "--method", "gt+none"]) == 2
    assert "DATASET" in capsys.readouterr().err
    assert cli_main.main(["eval", "somewhere", "-m", "gt+none", "--remote", "tcp/x:1"]) == 2
    assert "--map" in capsys.readouterr().err


def test_eval_missing_dataset_is_a_clear_error(tmp_path, capsys):
    assert cli_main.main(["eval", str(tmp_path / "nope"), "-m", "gt+none", "--no-progress"]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_eval_without_method_evaluates_the_default_method(tmp_path, capsys, monkeypatch):
    from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
    from reloc_service.cli import eval as cli_eval

    seen = {}
    monkeypatch.setattr(cli_eval, "_evaluate", lambda args: seen.setdefault("m", args.method) and 0)
    assert cli_main.main(["eval", str(tmp_path)]) == 0
    assert seen["m"] == [DEFAULT_METHOD]


def test_eval_list_methods(capsys):
    assert cli_main.main(["eval", "--list-methods"]) == 0
    out = capsys.readouterr().out
    from reloc_service.algorithms.relocalizers.factory import list_methods

    for m in list_methods():
        assert m["method"] in out


@pytest.mark.parametrize("command", cli_main.COMMANDS)
def test_every_subcommand_module_has_the_one_interface(command):
    module = cli_main.command_module(command)
    assert isinstance(module.HELP, str) and module.HELP and "\n" not in module.HELP
    assert callable(module.add_arguments) and callable(module.run)


@pytest.mark.parametrize("command", cli_main.COMMANDS)
def test_every_subcommand_has_its_help(command, capsys):
    parser = cli_main.build_parser(command)
    with pytest.raises(SystemExit) as exc:
        parser.parse_args([command, "--help"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: reloc {command} ")


def test_the_tool_commands_are_subcommands():
    assert TOOL_COMMANDS <= set(cli_main.COMMANDS)


def _readme_commands() -> list[tuple[str, str]]:
    """(name, one-line help) of each row ``| `reloc NAME` | HELP |`` of the README's table."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return re.findall(r"^\| `reloc (\w+)` \| (.+?) \|$", text, re.M)


def _help_commands(text: str) -> list[tuple[str, str]]:
    """(name, one-line help) of each subcommand listed by ``reloc --help`` (printed wide
    enough that no help line wraps)."""
    listing = text.split("  COMMAND\n", 1)[1].split("\n\n", 1)[0]
    return [tuple(line.split(None, 1)) for line in listing.splitlines()]


def test_the_readme_lists_the_commands_as_reloc_help_does(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit):
        cli_main.main(["--help"])
    listed = _help_commands(capsys.readouterr().out)
    assert [name for name, _ in listed] == list(cli_main.COMMANDS)
    assert _readme_commands() == listed


def test_synth_and_dataset_subcommands_are_wired():
    args = cli_main.build_parser("dataset").parse_args(["dataset", "check", "DS"])
    assert args.dataset_command == "check" and args.dataset == "DS"
    with pytest.raises(SystemExit) as exc:
        cli_main.build_parser("synth").parse_args(["synth", "--help"])
    assert exc.value.code == 0


def test_load_options_toml_and_json(tmp_path):
    toml = tmp_path / "o.toml"
    toml.write_text('[p3p]\nratio = 0.7\n[mapping]\nmin_parallax_deg = 2.0\n')
    assert load_options(toml) == {"p3p": {"ratio": 0.7}, "mapping": {"min_parallax_deg": 2.0}}
    js = tmp_path / "o.json"
    js.write_text(json.dumps({"sbi": {"width": 40}}))
    assert load_options(js) == {"sbi": {"width": 40}}


def test_load_options_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("ratio = 0.7\n")
    with pytest.raises(ConfigError, match="table of tables"):
        load_options(bad)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_options(broken)
    with pytest.raises(ConfigError, match="cannot read"):
        load_options(tmp_path / "missing.toml")


def test_module_entry_point_runs():
    proc = subprocess.run([sys.executable, "-m", "reloc_service.cli.main", "--version"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.startswith("reloc ")
