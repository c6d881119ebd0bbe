"""The first-party import graph of reloc, read from the source with ``ast``: imports inside
functions count, relative imports are resolved, ``from pkg import module`` is an import of the
module and ``importlib.import_module`` strings are followed. Its cycles (Tarjan's strongly
connected components) and its layer breaches are what tests/test_architecture.py asserts;
scripts/runtime_lines.py measures the service's closure with the same reader."""

from __future__ import annotations

import ast
import itertools
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

#: Top-level first-party packages and the folder (relative to the repo) each one lives in.
SOURCES = {"reloc_service": Path("."), "reloc_client": Path("clients")}

#: The layers of reloc_service, lowest first: each one is a folder of the package (``engine``
#: a module), and a module may import its own layer and those below it. docs/architecture.md
#: draws the same tree; tests/test_architecture.py checks that these are the package's folders.
LAYERS = ("core", "storage", "algorithms", "engine", "service", "tools", "cli")

#: What the layers below the tools may import from the client package: its numpy-only parts,
#: the wire format (with the quaternion and camera table both ends share) and the result type;
#: never the Zenoh client.
FROM_CLIENT = ("reloc_client.protocol", "reloc_client.result")
#: Third-party packages only some layers may import.
ZENOH_LAYERS = {"service", "tools", "cli", "client"}
TOOLS_EXTRA = {"skimage", "matplotlib"}  # pyproject's [tools] extra: only the tools use it


@dataclass
class Module:
    """One first-party module: its file and what it imports (absolute names -> first line)."""

    name: str
    path: Path
    imports: dict[str, int] = field(default_factory=dict)
    unresolved: list[int] = field(default_factory=list)  # lines of dynamic imports not followed

    @property
    def package(self) -> str:
        """The package relative imports start from."""
        return self.name if self.path.name == "__init__.py" else self.name.rpartition(".")[0]


def find_modules(root: Path, sources: dict[str, Path] = SOURCES) -> dict[str, Module]:
    """Every ``.py`` of the first-party packages under ``root``, by module name."""
    modules = {}
    for top, folder in sources.items():
        base = root / folder
        for path in sorted((base / top).rglob("*.py")):
            parts = path.relative_to(base).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            modules[name] = Module(name, path)
    return modules


def read_imports(module: Module) -> None:
    """Fill ``module.imports`` (and ``unresolved``) from its source, every scope included."""
    tree = ast.parse(module.path.read_text(encoding="utf-8"), str(module.path))
    constants = _module_constants(tree)
    for node in ast.walk(tree):
        line = getattr(node, "lineno", 0)
        for name in _imported_names(node, module, constants):
            if name is None:
                module.unresolved.append(line)
            else:
                module.imports.setdefault(name, line)


def _imported_names(node: ast.AST, module: Module,
                    constants: dict[str, list[str]]) -> Iterator[str | None]:
    """Absolute names ``node`` imports; None for an ``import_module`` that cannot be followed.
    ``from x import y`` yields ``x.y``: module ``x.y`` if there is one, else (a name defined
    in ``x``) :func:`build_graph` reads it as an import of ``x``."""
    if isinstance(node, ast.Import):
        yield from (alias.name for alias in node.names)
    elif isinstance(node, ast.ImportFrom):
        base = _absolute(node.module or "", node.level, module.package)
        yield from (base if alias.name == "*" else f"{base}.{alias.name}" for alias in node.names)
    elif isinstance(node, ast.Call) and _is_import_module(node.func):
        names = _import_module_targets(node, module, constants)
        yield from names if names else [None]


def _absolute(name: str, level: int, package: str) -> str:
    if not level:
        return name
    parts = package.split(".")
    base = parts[: len(parts) - level + 1]
    return ".".join(base + ([name] if name else []))


def _is_import_module(func: ast.expr) -> bool:
    return (isinstance(func, ast.Attribute) and func.attr == "import_module"
            and isinstance(func.value, ast.Name) and func.value.id == "importlib") or (
        isinstance(func, ast.Name) and func.id == "import_module")


def _import_module_targets(call: ast.Call, module: Module,
                           constants: dict[str, list[str]]) -> list[str]:
    """Every name ``importlib.import_module(name[, package])`` can import, when its arguments
    are literals, ``__name__``/``__package__``, a module-level table of strings indexed or
    looped over; [] when they are anything else."""
    if not call.args:
        return []
    names = _string_values(call.args[0], module, constants)
    package = _string_values(call.args[1], module, constants) if len(call.args) > 1 else [""]
    targets = []
    for name, pkg in itertools.product(names, package):
        level = len(name) - len(name.lstrip("."))
        targets.append(_absolute(name[level:], level, pkg) if level else name)
    return targets


def _string_values(node: ast.expr, module: Module, constants: dict[str, list[str]]) -> list[str]:
    """The strings ``node`` can evaluate to ([] if unknown)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, ast.Name) and node.id in ("__name__", "__package__"):
        return [module.name if node.id == "__name__" else module.package]
    if isinstance(node, ast.Name):
        return constants.get(node.id, [])
    if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name):
        return constants.get(node.value.id, [])
    if isinstance(node, ast.FormattedValue):
        return _string_values(node.value, module, constants)
    if isinstance(node, ast.JoinedStr):
        pieces = [_string_values(v, module, constants) for v in node.values]
        return ["".join(p) for p in itertools.product(*pieces)] if all(pieces) else []
    return []


def _module_constants(tree: ast.Module) -> dict[str, list[str]]:
    """The strings a name can hold: module-level dicts of strings (lazy-export tables, by
    their values) and tuples or lists of strings (module lists), and the variables of ``for``
    loops over those."""
    found = {}
    for statement in tree.body:
        target, items = _assigned_sequence(statement)
        strings = [v.value for v in items
                   if isinstance(v, ast.Constant) and isinstance(v.value, str)]
        if target and strings and len(strings) == len(items):
            found[target] = strings
    for node in ast.walk(tree):
        if (isinstance(node, ast.For) and isinstance(node.target, ast.Name)
                and isinstance(node.iter, ast.Name) and node.iter.id in found):
            found[node.target.id] = found[node.iter.id]
    return found


def _assigned_sequence(statement: ast.stmt) -> tuple[str | None, list[ast.expr | None]]:
    """(name, items) of ``name = {..}``, ``name: T = (..)`` or ``name = [..]``; a dict's items
    are its values."""
    value: ast.expr | None
    if isinstance(statement, ast.Assign) and len(statement.targets) == 1:
        target, value = statement.targets[0], statement.value
    elif isinstance(statement, ast.AnnAssign):
        target, value = statement.target, statement.value
    else:
        return None, []
    if not isinstance(target, ast.Name):
        return None, []
    if isinstance(value, ast.Dict):
        return target.id, list(value.values)
    if isinstance(value, (ast.Tuple, ast.List)):
        return target.id, list(value.elts)
    return None, []


def build_graph(modules: dict[str, Module]) -> dict[str, set[str]]:
    """First-party module -> the first-party modules it imports. An imported name that is not a
    module (``from pkg import function``) is an import of its longest module prefix; a
    package's ``__init__`` is not counted as imported by its submodules' import."""
    graph = {}
    for module in modules.values():
        graph[module.name] = {target for name in module.imports
                              if (target := _known_prefix(name, modules)) is not None
                              and target != module.name}
    return graph


def _known_prefix(name: str, modules: dict[str, Module]) -> str | None:
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


def load(root: Path, sources: dict[str, Path] = SOURCES) -> tuple[dict[str, Module],
                                                                   dict[str, set[str]]]:
    """The modules under ``root`` with their imports read, and their import graph."""
    modules = find_modules(root, sources)
    for module in modules.values():
        read_imports(module)
    return modules, build_graph(modules)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in sorted(graph):
        if start not in index:
            found += _tarjan_from(start, graph, index, low, stack, on_stack)
    return sorted(sorted(c) for c in found if len(c) > 1)


def _tarjan_from(start: str, graph: dict[str, set[str]], index: dict[str, int],
                 low: dict[str, int], stack: list[str], on_stack: set[str]) -> list[list[str]]:
    """Tarjan's algorithm from ``start``, with an explicit stack of iterators instead of
    recursion (a long import chain must not hit Python's recursion limit)."""
    components = []
    work = [(start, iter(sorted(graph.get(start, ()))))]
    _visit(start, index, low, stack, on_stack)
    while work:
        node, children = work[-1]
        child = next(children, None)
        if child is None:
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                components.append(_pop_component(node, stack, on_stack))
        elif child not in index:
            _visit(child, index, low, stack, on_stack)
            work.append((child, iter(sorted(graph.get(child, ())))))
        elif child in on_stack:
            low[node] = min(low[node], index[child])
    return components


def _visit(node: str, index: dict[str, int], low: dict[str, int], stack: list[str],
           on_stack: set[str]) -> None:
    index[node] = low[node] = len(index)
    stack.append(node)
    on_stack.add(node)


def _pop_component(root: str, stack: list[str], on_stack: set[str]) -> list[str]:
    component = []
    while True:
        node = stack.pop()
        on_stack.discard(node)
        component.append(node)
        if node == root:
            return component


def layer_of(name: str) -> str | None:
    """The layer of module ``name``: the folder of reloc_service it lives in (a name of
    :data:`LAYERS`; the package's own ``__init__`` is ``core``), ``client`` for reloc_client;
    None for a module of no layer."""
    parts = name.split(".")
    if parts[0] == "reloc_client":
        return "client"
    if parts[0] != "reloc_service":
        return None
    if len(parts) == 1:
        return "core"
    return parts[1] if parts[1] in LAYERS else None


def layer_folders(root: Path) -> set[str]:
    """The top-level folders (packages) and modules of reloc_service under ``root``, but its
    ``__init__``: what :data:`LAYERS` must name."""
    package = root / "reloc_service"
    return ({p.name for p in package.iterdir() if (p / "__init__.py").is_file()}
            | {p.stem for p in package.glob("*.py") if p.stem != "__init__"})


def _under(name: str, prefixes: Iterable[str]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def may_import(importer: str, imported: str) -> bool:
    """The layer rule for one first-party edge (docs/architecture.md, "Import rules"): a
    layer imports its own and those below it; the client only itself; below the tools, of
    the client only its numpy-only parts (:data:`FROM_CLIENT`)."""
    layer, target = layer_of(importer), layer_of(imported)
    if layer is None or target is None:
        return False
    if layer == "client":
        return target == "client"
    if target == "client":
        return layer in ("tools", "cli") or _under(imported, FROM_CLIENT)
    return LAYERS.index(target) <= LAYERS.index(layer)


def breaches(modules: dict[str, Module], graph: dict[str, set[str]]) -> list[str]:
    """Every import that breaks a layer rule, as "importer imports imported (file:line)"."""
    found = [f"{name} belongs to no layer (move it into a layer folder)" for name in sorted(graph)
             if layer_of(name) is None]
    for name in sorted(graph):
        module = modules[name]
        for imported in sorted(module.imports):
            target = _known_prefix(imported, modules)
            top = imported.split(".")[0]
            if target is not None and target != name and not may_import(name, target):
                found.append(_where(module, imported, f"{name} imports {target}"))
            elif top == "zenoh" and layer_of(name) not in ZENOH_LAYERS:
                found.append(_where(module, imported, f"{name} imports zenoh"))
            elif top in TOOLS_EXTRA and layer_of(name) != "tools":
                found.append(_where(module, imported, f"{name} imports {top} (the tools extra)"))
    return sorted(set(found))


def _where(module: Module, imported: str, text: str) -> str:
    return f"{text} ({module.path.name}:{module.imports[imported]})"


def unfollowed_dynamic_imports(modules: dict[str, Module]) -> list[str]:
    """``import_module`` calls the reader cannot follow, outside the CLI (which is the top layer:
    nothing imports it, so it cannot close a cycle or breach a layer)."""
    return [f"{m.name} ({m.path.name}:{line})" for m in modules.values()
            if layer_of(m.name) != "cli" for line in m.unresolved]


def closure(graph: dict[str, set[str]], roots: Iterable[str]) -> set[str]:
    """The modules reachable from ``roots``, plus the packages whose ``__init__`` Python runs
    to import them."""
    seen: set[str] = set()
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen or name not in graph:
            continue
        seen.add(name)
        todo += graph[name]
        todo += [".".join(name.split(".")[:end]) for end in range(1, name.count(".") + 1)]
    return seen
