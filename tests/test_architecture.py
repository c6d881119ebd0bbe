"""The layers of docs/architecture.md and an import graph without cycles, checked by parsing
every first-party module (imports inside functions and ``importlib`` strings included)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from archcheck import breaches, cycles, layer_of, load, unfollowed_dynamic_imports

ROOT = Path(__file__).resolve().parents[1]
CLIENT = ROOT / "clients" / "reloc_client"

#: The core's lower half: data types and I/O, below the algorithms and the engine.
BASE = {"errors", "geometry", "cameras", "frame", "map", "landmark_table", "triangulation",
        "landmarks", "features", "hamming", "storage", "snapshot_files", "feature_columns",
        "landmark_codec", "plugins", "progress", "mapping", "fileio", "numeric"}


@pytest.fixture(scope="module")
def repo():
    return load(ROOT)


def test_the_import_graph_has_no_cycle(repo):
    _, graph = repo
    found = cycles(graph)
    assert not found, "import cycles (strongly connected components):\n" + "\n".join(
        " <-> ".join(c) for c in found)


def test_every_import_respects_the_layers(repo):
    modules, graph = repo
    found = breaches(modules, graph)
    assert not found, "layer breaches:\n" + "\n".join(found)


def test_every_dynamic_import_is_followed(repo):
    """An ``import_module`` the reader cannot resolve could hide a cycle or a breach."""
    modules, _ = repo
    assert not unfollowed_dynamic_imports(modules)


def test_the_graph_sees_function_level_and_dynamic_imports(repo):
    """The reader is not blind to the imports that used to hide cycles."""
    modules, graph = repo
    assert len(modules) > 80 and all(layer_of(name) for name in graph)
    assert "reloc_service.tools.synth" in graph["reloc_service.tools.synth.cli"]  # in main_synth
    assert "reloc_service.tools.data.tum" in graph["reloc_service.tools.data"]  # import_module


def test_core_base_imports_no_algorithm_or_engine(repo):
    _, graph = repo
    for name, imported in graph.items():
        parts = name.split(".")
        if layer_of(name) == "core" and len(parts) > 1 and parts[1] in BASE:
            above = {m for m in imported if layer_of(m) == "core" and len(m.split(".")) > 1
                     and m.split(".")[1] not in BASE}
            assert not above, f"{name} imports {sorted(above)} (algorithms sit above it)"


def test_protocol_imports_only_msgpack_and_numpy():
    paths = sorted((CLIENT / "protocol").glob("*.py"))
    assert len(paths) > 1, "the wire protocol package clients/reloc_client/protocol/ is missing"
    stdlib = {"__future__", "dataclasses", "enum", "math", "typing", "collections", "struct", "re",
              "numbers", "reloc_client", "abc", "functools", "itertools", "sys", "io", "base64",
              "json"}
    for path in paths:
        tops = {name.split(".")[0] for node in ast.walk(ast.parse(path.read_text()))
                for name in _absolute_tops(node)}
        assert tops - stdlib <= {"msgpack", "numpy"}, (path.name, tops - stdlib)


def _absolute_tops(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom):
        return ["reloc_client" if node.level else node.module or ""]
    return []


# -- the checker on a planted cycle and planted breaches -------------------------------------

PLANTED = {
    "reloc_service/__init__.py": "",
    "reloc_service/geometry.py": "def f():\n    from .tools import a\n    import zenoh\n",
    "reloc_service/place/__init__.py": "",
    "reloc_service/place/sbi.py": "from ..geometry import f\nfrom reloc_client.client import C\n",
    "reloc_service/service/__init__.py": "from ..cli import main\n",
    "reloc_service/cli/__init__.py": "",
    "reloc_service/cli/main.py": "import reloc_service.service\n",
    "reloc_service/tools/__init__.py": "",
    "reloc_service/tools/a.py": "def f():\n    from . import b\n",
    "reloc_service/tools/b.py": "import importlib\n\n"
                                "def g():\n    importlib.import_module('reloc_service.tools.a')\n",
    "reloc_service/tools/lazy.py": "import importlib\n\n_LAZY = {'x': 'a'}\n\n"
                                   "def h(n):\n    importlib.import_module(f'.{_LAZY[n]}', "
                                   "__package__)\n    importlib.import_module(n)\n\n"
                                   "MODS = ('reloc_service.tools.b',)\n\ndef k():\n"
                                   "    for m in MODS:\n        importlib.import_module(m)\n",
    "reloc_service/unknown.py": "import skimage.data\n",
    "clients/reloc_client/__init__.py": "from reloc_service.place import sbi\n",
    "clients/reloc_client/client.py": "import zenoh\n",
}


@pytest.fixture
def planted(tmp_path):
    for rel, text in PLANTED.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    return load(tmp_path)


def test_a_planted_cycle_inside_functions_and_importlib_is_reported(planted):
    _, graph = planted
    assert cycles(graph) == [["reloc_service.cli.main", "reloc_service.service"],
                             ["reloc_service.tools.a", "reloc_service.tools.b"]]
    assert graph["reloc_service.tools.lazy"] == {"reloc_service.tools.a", "reloc_service.tools.b"}


def test_planted_layer_breaches_are_reported(planted):
    modules, graph = planted
    found = breaches(modules, graph)
    expected = ["reloc_service.geometry imports reloc_service.tools.a (geometry.py:2)",
                "reloc_service.geometry imports zenoh (geometry.py:3)",
                "reloc_service.service imports reloc_service.cli.main (__init__.py:1)",
                "reloc_service.place.sbi imports reloc_client.client (sbi.py:2)",
                "reloc_client imports reloc_service.place.sbi (__init__.py:1)",
                "reloc_service.unknown belongs to no layer (add it to CORE or a layer)",
                "reloc_service.unknown imports skimage (the tools extra) (unknown.py:1)"]
    assert sorted(found) == sorted(expected)
    assert unfollowed_dynamic_imports(modules) == ["reloc_service.tools.lazy (lazy.py:7)"]


def test_a_planted_clean_tree_passes(planted, tmp_path):
    """Remove the planted faults: nothing is reported (the checks are not always-fail)."""
    for rel in ("reloc_service/unknown.py", "reloc_service/tools/lazy.py"):
        (tmp_path / rel).unlink()
    (tmp_path / "reloc_service/geometry.py").write_text("def f():\n    import numpy\n")
    (tmp_path / "reloc_service/service/__init__.py").write_text("from ..place import sbi\n")
    (tmp_path / "reloc_service/tools/b.py").write_text("from . import a\n")
    (tmp_path / "reloc_service/tools/a.py").write_text("import zenoh\nimport matplotlib\n")
    (tmp_path / "clients/reloc_client/__init__.py").write_text("import zenoh\n")
    (tmp_path / "reloc_service/place/sbi.py").write_text("from reloc_client.protocol import P\n")
    (tmp_path / "clients/reloc_client/protocol.py").write_text("import numpy\n")
    modules, graph = load(tmp_path)
    assert cycles(graph) == [] and breaches(modules, graph) == []
