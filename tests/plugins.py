"""Encoder plugins written into a temporary folder for tests: a package, its spec file and the
distribution metadata (`*.dist-info` with entry points) that the registry finds on `sys.path`."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from mftcn_bench.core import identity

TRUE_STATE_SPEC = (Path(__file__).resolve().parent.parent / "encoders" / "true-state.toml").read_text()


class TmpPlugin:
    """A plugin distribution `package` (version `version`) registering `encoders` = {name: "module:Class"},
    each with a copy of `spec` as its spec file."""

    def __init__(self, root: Path, package: str, version: str, modules: dict[str, str],
                 encoders: dict[str, str], spec: str = TRUE_STATE_SPEC) -> None:
        self.root, self.package = root, package
        pkg = root / package
        (pkg / "specs" / "encoders").mkdir(parents=True)
        (pkg / "__init__.py").write_text("")
        for module, source in modules.items():
            (pkg / f"{module}.py").write_text(source)
        for name in encoders:
            (pkg / "specs" / "encoders" / f"{name}.toml").write_text(spec)
        self.dist = root / f"{package}-{version}.dist-info"
        self.dist.mkdir()
        self.set_version(version)
        (self.dist / "top_level.txt").write_text(f"{package}\n")
        (self.dist / "entry_points.txt").write_text(
            "[mftcn_bench.encoders]\n" + "".join(f"{n} = {package}.{v}\n" for n, v in encoders.items()))

    def set_version(self, version: str) -> None:
        (self.dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {self.package}\nVersion: {version}\n")

    def edit(self, module: str, source: str) -> None:
        (self.root / self.package / f"{module}.py").write_text(source)
        for name in [m for m in sys.modules if m == self.package or m.startswith(f"{self.package}.")]:
            del sys.modules[name]  # the next load imports the edited source
        importlib.invalidate_caches()


def install(monkeypatch, root: Path, *args, **kwargs) -> TmpPlugin:
    plugin = TmpPlugin(root, *args, **kwargs)
    monkeypatch.setattr(sys, "path", [str(root), *sys.path])
    identity._package_root.cache_clear()
    importlib.invalidate_caches()
    return plugin
