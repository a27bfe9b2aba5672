"""Every identity the harness keys an artifact by: datasets, feature caches, encoder fits, experts and runs.

An identity is a content hash of what produced the artifact: its inputs (resolved configs, seeds, the
fingerprints of the artifacts it was made from), the versions of the libraries that compute it, and its
code. Code is identified per component by `code_identity`: the normal form of every module of the component's
import closure (followed through `import` statements of the harness and of the component's own top-level
package), plus, for a plugin, its distribution's name and version. The normal form is the module's syntax
tree without docstrings, comments, blank lines or positions (`normal_form`): what the code does, not how
its text is laid out. So editing a collector's code re-keys its datasets, editing `rl/ppo.py` re-keys every
control run, and bumping a plugin's version or editing its code re-keys that plugin's runs, while fixing a
comment or a docstring, or editing the report code, re-keys nothing.

Imports through strings (`importlib.import_module("x")`, entry points) are not followed; the runner adds
the encoder's and the task's classes explicitly.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import json
import marshal
import sys
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from importlib.metadata import distributions, packages_distributions
from pathlib import Path
from typing import Any

from mftcn_bench.core.provenance import BASE_PACKAGES, TRACKED_PACKAGES, content_hash, versions

HARNESS = "mftcn_bench"


@dataclass(frozen=True)
class CodeIdentity:
    """The code of one component: where it lives and a digest of its import closure's source."""

    module: str                    # the component's module (`mftcn_bench.encoders.mftcn`, `my_plugin.enc`)
    distribution: str | None       # the installed distribution that ships it (`mftcn-bench`, `my-plugin`)
    version: str | None            # that distribution's version
    source: str                    # sha256 (16 hex) of the closure's module names and normal forms
    editable: bool = False         # installed in editable / development mode (its source can change in place)

    @property
    def is_plugin(self) -> bool:
        return self.module.split(".")[0] != HARNESS

    def key(self) -> dict[str, Any]:
        """What the identity hashes: not `editable`, so the same code keys the same however installed."""
        return {"module": self.module, "distribution": self.distribution, "version": self.version,
                "source": self.source}


@functools.cache
def _package_root(top: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):  # `__main__` of `python -c`, a module without a spec
        return None
    if spec is None:
        return None
    if spec.submodule_search_locations:
        return Path(next(iter(spec.submodule_search_locations)))
    return Path(spec.origin).parent if spec.origin else None


def _module_file(module: str) -> Path | None:
    top, *rest = module.split(".")
    root = _package_root(top)
    if root is None:
        return None
    if not rest and not root.joinpath("__init__.py").is_file():
        return root / f"{top}.py"  # a single-module distribution
    base = root.joinpath(*rest)
    for candidate in (base / "__init__.py", base.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


@functools.lru_cache(maxsize=1024)
def _parse(source: bytes) -> ast.Module:
    """A module's syntax tree, keyed by its bytes (an edited file is parsed anew); never modified."""
    return ast.parse(source)


def _tree(path: Path) -> ast.Module:
    return _parse(path.read_bytes())


_DOCUMENTED = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)


def normal_form(path: Path) -> bytes:
    """What a module's code does, without its layout: its syntax tree written out with every docstring
    dropped and no line or column numbers (comments and blank lines never reach the tree)."""
    return _written(_tree(path)).encode()


def _has_docstring(node: ast.AST) -> bool:
    if not isinstance(node, _DOCUMENTED) or not node.body:
        return False
    first = node.body[0]
    return isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str)


def _written(node: object) -> str:
    """`ast.dump` without positions, skipping docstrings (the cached tree is read, never changed)."""
    if isinstance(node, ast.AST):
        fields = {name: getattr(node, name, None) for name in node._fields}
        if _has_docstring(node):
            fields["body"] = fields["body"][1:]
        return f"{type(node).__name__}({', '.join(f'{k}={_written(v)}' for k, v in fields.items())})"
    if isinstance(node, list):
        return f"[{', '.join(_written(item) for item in node)}]"
    return repr(node)


def _imports(module: str, path: Path) -> set[str]:
    """Absolute names of every module `path` imports anywhere (also inside functions)."""
    tree = _tree(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                origin = ".".join(parts[: len(parts) - node.level + 1])
                origin = f"{origin}.{node.module}" if node.module else origin
            else:
                origin = node.module or ""
            found.add(origin)
            found.update(f"{origin}.{alias.name}" for alias in node.names)  # `from pkg import submodule`
    return found


def _closure(roots: tuple[str, ...], tracked: frozenset[str]) -> tuple[tuple[str, Path], ...]:
    """(module, file) of every module in the import closure of `roots`, within the `tracked` packages."""
    seen: dict[str, Path] = {}
    todo = list(roots)
    while todo:
        module = todo.pop()
        if module in seen or module.split(".")[0] not in tracked:
            continue
        path = _module_file(module)
        if path is None:
            continue
        seen[module] = path
        parts = module.split(".")
        todo.extend(".".join(parts[:i]) for i in range(1, len(parts)))  # parents' __init__ run on import
        todo.extend(_imports(module, path))
    return tuple(sorted(seen.items()))


def source_digest(modules: Iterable[str]) -> str:
    """sha256 (16 hex) of the import closure of `modules`: every module's name and normal form."""
    roots = tuple(sorted(set(modules)))
    tracked = frozenset({HARNESS, *(m.split(".")[0] for m in roots)})
    digest = hashlib.sha256()
    for module, path in _closure(roots, tracked):
        digest.update(module.encode() + b"\0" + hashlib.sha256(normal_form(path)).digest())
    return digest.hexdigest()[:16]


@functools.cache
def _distributions_by_package(path: tuple[str, ...]) -> Mapping[str, list[str]]:
    return packages_distributions()  # scans every installed distribution: once per sys.path


def _distribution_of(top: str) -> tuple[str | None, str | None, bool]:
    """(name, version, editable) of the installed distribution that ships package `top`."""
    for name in _distributions_by_package(tuple(sys.path)).get(top, []):
        # An egg-info beside a source checkout can shadow the installed metadata; prefer the installed one.
        found = sorted(distributions(name=name), key=lambda d: d.read_text("direct_url.json") is None)
        if not found:
            continue
        dist = found[0]
        direct = dist.read_text("direct_url.json")
        editable = bool(direct) and bool(json.loads(direct).get("dir_info", {}).get("editable", False))
        return dist.metadata["Name"], dist.version, editable
    return None, None, False


def module_of(component: object) -> str:
    """The module that defines a class, a function, a partial, a bound method or an instance."""
    target = component
    while isinstance(target, functools.partial):
        target = target.func
    target = getattr(target, "__func__", target)  # a bound method's function
    module = getattr(target, "__module__", None)
    if not isinstance(module, str):
        module = type(target).__module__
    return module


def code_identity(*components: object) -> CodeIdentity:
    """The code of `components` (classes, functions, instances or module names) as one identity; the first
    names the distribution recorded (the plugin's, when it is one)."""
    modules = [c if isinstance(c, str) else module_of(c) for c in components]
    dist, version, editable = _distribution_of(modules[0].split(".")[0])
    source = source_digest(modules)
    if modules[0] == "__main__":  # a script's own function (no file to read): its compiled code
        code = getattr(getattr(components[0], "__func__", components[0]), "__code__", None)
        extra = marshal.dumps(code) if code is not None else repr(components[0]).encode()
        source = hashlib.sha256(source.encode() + extra).hexdigest()[:16]
    return CodeIdentity(modules[0], dist, version, source, editable)


def library_versions() -> dict[str, str | None]:
    """The versions of the libraries that compute results (they change numbers, so they key artifacts)."""
    found = versions()
    return {name: found[name] for name in ("python", *TRACKED_PACKAGES, *BASE_PACKAGES)}


def _key(kind: str, inputs: Mapping[str, Any], code: CodeIdentity) -> str:
    return content_hash({"kind": kind, "inputs": dict(inputs), "code": code.key(),
                         "libraries": library_versions()})


def dataset_id(config: Mapping[str, Any], collector: object, format_version: int, renderer: str = "") -> str:
    """A dataset: its config, the file format, the collector's code and the GL renderer that draws its
    frames (a GPU's EGL and Mesa's llvmpipe need not give the same pixels)."""
    return _key("dataset", {"config": dict(config), "format": format_version, "renderer": renderer},
                code_identity(collector))


def feature_cache_id(dataset_fingerprint: str, base_identity: Mapping[str, Any], base: object,
                     format_version: int, placement: Mapping[str, Any] | None = None) -> str:
    """A frozen base's per-frame features of one dataset: the base's settings and weights' checksum, the
    cache format, the base's code and (off the CPU) the device that computed them."""
    inputs = {"dataset": dataset_fingerprint, "base": dict(base_identity), "format": format_version}
    if placement is not None and placement.get("device") != "cpu":
        inputs["placement"] = dict(placement)
    return _key("feature-cache", inputs, code_identity(base, "mftcn_bench.encoders.feature_cache"))


def encoder_fit_key(encoder_config: Mapping[str, Any], dataset_fingerprint: str, seed: int,
                    encoder_code: CodeIdentity, base_identity: Mapping[str, Any] | None = None,
                    placement: Mapping[str, Any] | None = None) -> str:
    """A trained encoder: shared by every task whose dataset and encoder config are the same. `placement`
    (`Placement.identity()`) enters only off the CPU: a CPU key holds no placement."""
    inputs: dict[str, Any] = {"encoder": dict(encoder_config), "dataset": dataset_fingerprint, "seed": seed}
    if base_identity is not None:
        inputs["base"] = dict(base_identity)
    if placement is not None and placement.get("device") != "cpu":
        inputs["placement"] = dict(placement)
    return _key("encoder-fit", inputs, encoder_code)


def expert_key(env_config: Mapping[str, Any], ppo_config: Mapping[str, Any], seed: int) -> str:
    """A state-based expert policy (the cheetah demonstrations' teacher)."""
    return _key("expert", {"env": dict(env_config), "ppo": dict(ppo_config), "seed": seed},
                code_identity("mftcn_bench.rl.expert"))


@dataclass(frozen=True)
class RunCode:
    """The code a run depends on: its encoder's, its task's and the runner's."""

    encoder: CodeIdentity
    task: CodeIdentity
    harness: str   # source digest of the runner's closure

    def as_dict(self) -> dict[str, Any]:
        return {"encoder": asdict(self.encoder), "task": asdict(self.task), "harness": self.harness}

    def key(self) -> dict[str, Any]:
        return {"encoder": self.encoder.key(), "task": self.task.key(), "harness": self.harness}


def run_code(encoder_class: type, task: object) -> RunCode:
    return RunCode(code_identity(encoder_class), code_identity(task), source_digest(["mftcn_bench.run.runner"]))


def run_id(config: Mapping[str, Any], preset: str, seed: int, dataset_fingerprint: str, code: RunCode,
           placement: Mapping[str, Any] | None = None, base: Mapping[str, Any] | None = None) -> str:
    """One (encoder, task, preset, seed) run: the resolved config, the dataset and all the code involved,
    (off the CPU, as `encoder_fit_key`) the device it computed on, and the encoder's frozen base with its
    weights' checksum (the config names a weights file only by its path)."""
    inputs = {"kind": "run", "config": dict(config), "preset": preset, "seed": seed,
              "dataset": dataset_fingerprint, "code": code.key(), "libraries": library_versions()}
    if base is not None:
        inputs["base"] = dict(base)
    if placement is not None and placement.get("device") != "cpu":
        inputs["placement"] = dict(placement)
    return content_hash(inputs)
