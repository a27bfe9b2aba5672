"""Imports point one way: a module never imports from a layer above its own (lazy imports included).

Layers, lowest first: the run core, simulation, data, encoders, RL, tasks, results, a run, diagnostics, sweeps,
the performance suite, the command line. A layer may import any layer below it and itself.
"""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "mftcn_bench"
LAYERS = ["core", "sim", "data", "encoders", "rl", "tasks", "results", "run", "diagnose", "orchestration", "perf",
          "cli"]


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "mftcn_bench":
        return None
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else 0


def _imports(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names if node.module == "mftcn_bench")
    return found


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
