"""The layering rules of ARCHITECTURE.md, checked by parsing imports."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SERVICE = ROOT / "reloc_service"
CLIENT = ROOT / "clients" / "reloc_client"

CORE = {"errors", "geometry", "cameras", "frame", "map", "triangulation", "features", "storage",
        "plugins", "progress", "mapping", "fileio", "numeric"}
ALGORITHMS = {"place", "pose", "ferns", "relocalizers"}


def imports_of(path: Path) -> set[str]:
    """Absolute module names imported by ``path`` (relative imports resolved)."""
    tree = ast.parse(path.read_text())
    pkg = path.relative_to(ROOT if SERVICE in path.parents else CLIENT.parent).with_suffix("").parts[:-1]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(pkg[: len(pkg) - node.level + 1])
                mod = ".".join(base + ([node.module] if node.module else []))
                found.add(mod)
                found.update(f"{mod}.{a.name}" for a in node.names)
            else:
                found.add(node.module or "")
    return found


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "reloc_service" or len(parts) < 2:
        return None
    return parts[1]


def test_client_never_imports_service():
    for path in CLIENT.rglob("*.py"):
        bad = [m for m in imports_of(path) if m.startswith("reloc_service")]
        assert not bad, f"{path} imports {bad}"


def test_protocol_imports_only_msgpack_and_numpy():
    paths = sorted((CLIENT / "protocol").glob("*.py"))
    assert len(paths) > 1, "the wire protocol package clients/reloc_client/protocol/ is missing"
    for path in paths:
        third_party = {m.split(".")[0] for m in imports_of(path)} - {
            "__future__", "dataclasses", "enum", "math", "typing", "collections", "struct", "re",
            "numbers", "reloc_client", "abc", "functools", "itertools", "sys", "io", "base64",
            "json"}
        assert third_party <= {"msgpack", "numpy"}, (path.name, third_party)


def test_core_imports_no_algorithm_service_eval_or_cli():
    for path in SERVICE.glob("*.py"):
        if path.stem not in CORE:
            continue
        layers = {layer_of(m) for m in imports_of(path)} - {None}
        bad = layers - CORE
        assert not bad, f"core module {path.name} imports {bad}"


def test_algorithms_import_core_and_algorithms_only():
    for layer in ALGORITHMS:
        for path in (SERVICE / layer).rglob("*.py"):
            layers = {layer_of(m) for m in imports_of(path)} - {None}
            bad = layers - CORE - ALGORITHMS
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_only_service_clients_and_tests_import_zenoh():
    allowed = {"service", "bench", "eval", "cli"}  # eval/bench use the client for remote runs
    for path in SERVICE.rglob("*.py"):
        mods = imports_of(path)
        if any(m == "zenoh" or m.startswith("zenoh.") for m in mods):
            rel = path.relative_to(SERVICE).parts
            assert rel[0] == "service", f"{path.relative_to(ROOT)} imports zenoh"
            assert rel[0] in allowed
