"""The layers of docs/architecture.md and an import graph without cycles, checked by parsing
every first-party module (imports inside functions and ``importlib`` strings included)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
from archcheck import (
    LAYERS,
    breaches,
    cycles,
    layer_folders,
    layer_of,
    load,
    unfollowed_dynamic_imports,
)

ROOT = Path(__file__).resolve().parents[1]
CLIENT = ROOT / "clients" / "reloc_client"

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


def test_the_layers_are_the_package_folders():
    """Every folder (and module) of reloc_service is a layer of LAYERS, and every layer a
    folder: the layer rule is a prefix rule read from the tree."""
    assert layer_folders(ROOT) == set(LAYERS)


def test_the_architecture_document_draws_the_layers_in_order():
    """docs/architecture.md's layer table names the layers top-down, each with its folder."""
    rows = re.findall(r"^\| \*\*(\w+)\*\* \| `(reloc_service/[\w./]+|clients/[\w/]+)`",
                      (ROOT / "docs" / "architecture.md").read_text(), re.M)
    package = [(name, path) for name, path in rows if path.startswith("reloc_service/")]
    assert [name for name, _ in package] == list(reversed(LAYERS))
    for name, path in package:
        assert path.rstrip("/") in (f"reloc_service/{name}", f"reloc_service/{name}.py"), path


def test_protocol_imports_only_msgpack_and_numpy():
    paths = sorted((CLIENT / "protocol").glob("*.py"))
    assert len(paths) > 1, "the wire protocol package clients/reloc_client/protocol/ is missing"
    stdlib = {"__future__", "dataclasses", "enum", "math", "typing", "collections", "struct", "re",
              "numbers", "reloc_client", "abc", "functools", "itertools", "sys", "io", "base64",
              "json", "reprlib"}
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
    "reloc_service/core/__init__.py": "",
    "reloc_service/core/geometry.py": "def f():\n    from ..tools import a\n    import zenoh\n",
    "reloc_service/storage/__init__.py": "",
    "reloc_service/storage/snapshot.py": "from ..algorithms.place import sbi\n",
    "reloc_service/algorithms/__init__.py": "",
    "reloc_service/algorithms/place/__init__.py": "",
    "reloc_service/algorithms/place/sbi.py": "from ...core.geometry import f\n"
                                             "from reloc_client.client import C\n",
    "reloc_service/engine.py": "from .algorithms.place import sbi\n",
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
    "clients/reloc_client/__init__.py": "from reloc_service.algorithms.place import sbi\n",
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
    expected = ["reloc_service.core.geometry imports reloc_service.tools.a (geometry.py:2)",
                "reloc_service.core.geometry imports zenoh (geometry.py:3)",
                "reloc_service.storage.snapshot imports reloc_service.algorithms.place.sbi "
                "(snapshot.py:1)",
                "reloc_service.service imports reloc_service.cli.main (__init__.py:1)",
                "reloc_service.algorithms.place.sbi imports reloc_client.client (sbi.py:2)",
                "reloc_client imports reloc_service.algorithms.place.sbi (__init__.py:1)",
                "reloc_service.unknown belongs to no layer (move it into a layer folder)",
                "reloc_service.unknown imports skimage (the tools extra) (unknown.py:1)"]
    assert sorted(found) == sorted(expected)
    assert unfollowed_dynamic_imports(modules) == ["reloc_service.tools.lazy (lazy.py:7)"]


def test_a_planted_clean_tree_passes(planted, tmp_path):
    """Remove the planted faults: nothing is reported (the checks are not always-fail)."""
    for rel in ("reloc_service/unknown.py", "reloc_service/tools/lazy.py"):
        (tmp_path / rel).unlink()
    (tmp_path / "reloc_service/core/geometry.py").write_text("def f():\n    import numpy\n")
    (tmp_path / "reloc_service/service/__init__.py").write_text(
        "from ..algorithms.place import sbi\n")
    (tmp_path / "reloc_service/storage/snapshot.py").write_text("from ..core import geometry\n")
    (tmp_path / "reloc_service/tools/b.py").write_text("from . import a\n")
    (tmp_path / "reloc_service/tools/a.py").write_text("import zenoh\nimport matplotlib\n")
    (tmp_path / "clients/reloc_client/__init__.py").write_text("import zenoh\n")
    (tmp_path / "reloc_service/algorithms/place/sbi.py").write_text(
        "from reloc_client.protocol import P\n")
    (tmp_path / "clients/reloc_client/protocol.py").write_text("import numpy\n")
    modules, graph = load(tmp_path)
    assert cycles(graph) == [] and breaches(modules, graph) == []
