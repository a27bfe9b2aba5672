"""Imports point one way: a module never imports from a layer above its own (lazy imports included), and
modules never import each other in a circle, inside a layer too.

Layers, lowest first: the run core, simulation, data, encoders, RL, tasks, results, a run, diagnostics, sweeps,
the performance suite, the command line. A layer may import any layer below it and itself.
"""

import ast
from collections import deque
from collections.abc import Iterator
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "mftcn_bench"
LAYERS = ["core", "sim", "data", "encoders", "rl", "tasks", "results", "run", "diagnose", "orchestration", "perf",
          "cli"]


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "mftcn_bench":
        return None
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else 0


def _imports(path: Path, runtime: bool = False) -> set[str]:
    """Every module `path` imports, at module level or in a function; `from m import x` gives m and m.x
    (x may be a submodule). With `runtime`, not those under `if TYPE_CHECKING:`, which never run."""
    found = set()
    for node in _nodes(ast.parse(path.read_text()), runtime):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def _nodes(tree: ast.AST, runtime: bool) -> Iterator[ast.AST]:
    todo = [tree]
    while todo:
        node = todo.pop()
        if runtime and isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING"):
            todo.extend(node.orelse)
            continue
        yield node
        todo.extend(ast.iter_child_nodes(node))


def _import_graph(package: Path) -> dict[str, set[str]]:
    """Module name -> the modules of `package` it imports when it runs (a package is its `__init__`)."""
    names = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return {name: {m for m in _imports(path, runtime=True) if m in names and m != name}
            for name, path in names.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle, [a, b, ..., a], for each group of modules that reach each other by imports: the shortest
    from the group's first module back to itself, so the message names a circle one can read and break."""
    cycles = []
    for group in _groups(graph):
        start = min(group)
        came_from: dict[str, str] = {}
        todo = deque([start])
        while start not in came_from:  # breadth first inside the group; it always leads back to start
            node = todo.popleft()
            for target in sorted(graph[node] & group):
                if target not in came_from:
                    came_from[target] = node
                    todo.append(target)
        path = [start]
        while len(path) == 1 or path[-1] != start:
            path.append(came_from[path[-1]])
        cycles.append(path[::-1])
    return sorted(cycles)


def _groups(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            group = set()
            while node not in group:
                group.add(stack.pop())
            if len(group) > 1:
                groups.append(group)

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return groups


def test_every_module_belongs_to_a_layer():
    loose = [p.name for p in PACKAGE.glob("*.py") if p.name != "__init__.py"]
    assert not loose, f"modules outside the layers: {loose}"
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders <= set(LAYERS), folders - set(LAYERS)


def test_imports_point_down():
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        own = _layer(module)
        for imported in _imports(path):
            theirs = _layer(imported)
            if theirs is not None and theirs > own:
                upward.append(f"{module} ({LAYERS[own]}) imports {imported} ({LAYERS[theirs]})")
    assert not upward, "\n".join(upward)


def test_the_check_finds_an_upward_import(tmp_path):
    bad = tmp_path / "mod.py"
    bad.write_text("def f():\n    from mftcn_bench.results.store import ResultStore\n")
    assert "mftcn_bench.results.store" in _imports(bad) and _layer("mftcn_bench.results.store") > _layer(
        "mftcn_bench.data.dataset")


# Circles known when the check was added, in files outside that change: each is to be broken, then removed here.
KNOWN_CYCLES: list[list[str]] = []  # none: a circle found here is fixed, not listed


def test_no_import_cycles():
    """A module that imports another, however lazily, must not be imported back by it, directly or around a
    circle: a circle runs half-initialised modules in an order that depends on who imports first."""
    cycles = _cycles(_import_graph(PACKAGE))
    new = [" -> ".join(c) for c in cycles if c not in KNOWN_CYCLES]
    gone = [" -> ".join(c) for c in KNOWN_CYCLES if c not in cycles]
    assert not new, "import cycles:\n" + "\n".join(new)
    assert not gone, "no longer a cycle, remove it from KNOWN_CYCLES:\n" + "\n".join(gone)


def test_the_check_finds_an_import_cycle(tmp_path):
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "a.py").write_text("from pkg.b import g\n\n\ndef f():\n    return g()\n")
    (package / "b.py").write_text("def g():\n    from pkg import a\n\n    return a\n")
    assert _cycles(_import_graph(package)) == [["pkg.a", "pkg.b", "pkg.a"]]
    (package / "b.py").write_text("from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n    from pkg import a\n")
    assert _cycles(_import_graph(package)) == []  # an import for type hints only never runs
