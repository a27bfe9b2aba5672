"""The registry of encoders and tasks, fed only by entry points.

Groups `mftcn_bench.encoders` and `mftcn_bench.tasks`. An entry point's name is the variant
(`mftcn5`, `cartpole-probe`), its value the implementing class. The variant's spec file is
`specs/encoders/<name>.toml` or `specs/tasks/<name>.toml` in the nearest package, from the entry point's
module up to its top level, that ships one (`acme.vision.enc:Encoder` looks in `acme.vision.enc`, then
`acme.vision`, then `acme`), so a plugin inside a namespace package (`acme.vision`) keeps its specs beside
its code.
Resolving a name reads spec files only; the implementation is imported when a variant is used (and by
`list`, which checks every one), so a plugin that fails to import costs a warning, never the rest of the
harness.
"""

from __future__ import annotations

import functools
import importlib.resources
import importlib.util
import sys
import warnings
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Any, Literal

from mftcn_bench.core.errors import BenchError, BenchWarning, SpecError, did_you_mean
from mftcn_bench.core.specs import EncoderSpec, TaskSpec, load_spec_tree

Kind = Literal["encoders", "tasks"]
GROUPS: dict[Kind, str] = {"encoders": "mftcn_bench.encoders", "tasks": "mftcn_bench.tasks"}


class PluginWarning(BenchWarning):
    """A registered plugin that cannot be used (import failure, missing spec)."""


@dataclass(frozen=True)
class Entry:
    """One registered variant: its entry point and its parsed spec."""

    kind: Kind
    entry_point: EntryPoint
    spec: EncoderSpec | TaskSpec
    registered_by: EntryPoint  # the variant's own entry point, or its family's (`<family>.family`)

    @property
    def name(self) -> str:
        return self.entry_point.name

    @property
    def description(self) -> str:
        return self.spec.description

    def load(self) -> type:
        """Import and return the implementing class; an import failure becomes a one-line error."""
        try:
            return self.entry_point.load()
        except Exception as exc:  # noqa: BLE001 - any plugin failure is reported the same way
            raise BenchError(
                f"{self.kind[:-1]} {self.name!r} failed to import ({self.entry_point.value}): "
                f"{type(exc).__name__}: {exc}"
            ) from None


FAMILY_SUFFIX = ".family"  # an entry point `mftcn.family = "pkg.mod:Class"` serves every spec of that family


def _spec_folder(package: str, folder: str):
    try:
        return importlib.resources.files(package) / "specs" / folder
    except Exception as exc:  # noqa: BLE001 - a broken plugin package
        raise SpecError(f"package {package!r} failed to import: {type(exc).__name__}: {exc}") from None


def _packages_of(module: str) -> list[str]:
    """The packages `module` sits in, nearest first (the module itself is not imported to find its specs)."""
    parts = module.split(".")
    return [".".join(parts[:i]) for i in range(len(parts) - 1, 0, -1)] or [module]


def _has(package: str, *path: str) -> bool:
    """Whether `package` ships `specs/<path>`; found without running the package's `__init__`."""
    try:
        spec = importlib.util.find_spec(package)
    except Exception:  # noqa: BLE001 - a broken parent package: not this one
        return False
    locations = (spec.submodule_search_locations or []) if spec is not None else []
    return any(Path(location, "specs", *path).exists() for location in locations)


def _spec_package(module: str, kind: Kind, name: str | None = None) -> str:
    """The nearest package around `module` holding `specs/<kind>/<name>.toml` (or, without a name, a
    `specs/<kind>` folder); the top-level package when none does (its error then names the file)."""
    path = (kind, f"{name}.toml") if name is not None else (kind,)
    return next((package for package in _packages_of(module) if _has(package, *path)), module.split(".")[0])


def _spec_data(package: str, kind: Kind, name: str) -> dict[str, Any]:
    """The spec file `specs/<kind>/<name>.toml` of `package` with `extends` and `dataset = "<name>"`
    resolved (`load_spec_tree`)."""
    def read(folder: str, file: str) -> str:
        resource = _spec_folder(package, folder) / f"{file}.toml"
        try:
            return resource.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise SpecError(f"no spec file specs/{folder}/{file}.toml in package {package!r}") from None

    return load_spec_tree(kind, name, read, f"{package}/specs")


def _make_spec(kind: Kind, name: str, data: dict[str, Any]) -> EncoderSpec | TaskSpec:
    if kind == "encoders":
        return EncoderSpec.from_dict(name, data)
    return TaskSpec.from_dict(name, data)


def _family_variants(kind: Kind, ep: EntryPoint) -> dict[str, tuple[EntryPoint, dict[str, Any]]]:
    """Every spec file of the family that `ep` (`<family>.family`) registers, in its own package."""
    family, package = ep.name[: -len(FAMILY_SUFFIX)], _spec_package(ep.module, kind)
    out = {}
    for resource in sorted(_spec_folder(package, kind).iterdir(), key=lambda r: r.name):
        name = resource.name.removesuffix(".toml")
        if not resource.name.endswith(".toml") or name.startswith("_"):  # `_name.toml`: a template
            continue
        data = _spec_data(package, kind, name)
        if data.get("family") == family:
            out[name] = (EntryPoint(name, ep.value, ep.group), data)
    return out


@functools.cache
def _entry_points(group: str, path: tuple[str, ...]) -> tuple[EntryPoint, ...]:
    return tuple(entry_points(group=group))  # reading every distribution's metadata: once per sys.path


def _spec_stamps(kind: Kind, eps: tuple[EntryPoint, ...]) -> tuple:
    """(file, mtime) of every spec file the scan of `kind` may read: a changed or added file rescans."""
    stamps = []
    for package in sorted({_spec_package(ep.module, kind) for ep in eps}):
        try:
            root = Path(str(importlib.resources.files(package) / "specs"))
        except Exception:  # noqa: BLE001 - the scan reports a broken package itself
            continue
        for folder in (root / kind, root / "datasets"):
            if folder.is_dir():
                stamps += [(str(p), p.stat().st_mtime_ns) for p in folder.glob("*.toml")]
    return tuple(sorted(stamps))


_SCANS: dict[tuple, tuple[dict[str, Entry], dict[str, str]]] = {}


def _scan(kind: Kind) -> tuple[dict[str, Entry], dict[str, str]]:
    """(usable variants by name, unusable ones by name with the reason); remembered until the installed
    entry points or a spec file change (reports ask for every stored run's variant)."""
    eps = _entry_points(GROUPS[kind], tuple(sys.path))
    key = (kind, eps, _spec_stamps(kind, eps))
    if key not in _SCANS:
        _SCANS[key] = _scan_now(kind, eps)
    found, broken = _SCANS[key]
    return dict(found), dict(broken)


def _scan_now(kind: Kind, eps: tuple[EntryPoint, ...]) -> tuple[dict[str, Entry], dict[str, str]]:
    found: dict[str, Entry] = {}
    broken: dict[str, str] = {}
    families = []
    for ep in eps:
        if ep.name.endswith(FAMILY_SUFFIX):
            families.append(ep)
            continue
        if ep.name in found or ep.name in broken:
            continue  # the same distribution seen twice on sys.path
        try:
            package = _spec_package(ep.module, kind, ep.name)
            found[ep.name] = Entry(kind, ep, _make_spec(kind, ep.name, _spec_data(package, kind, ep.name)), ep)
        except BenchError as exc:
            broken[ep.name] = str(exc)
    for family in families:  # a variant with an entry point of its own keeps it
        try:
            variants = _family_variants(kind, family)
        except BenchError as exc:
            broken[family.name] = str(exc)
            continue
        for name, (ep, data) in variants.items():
            if name in found or name in broken:
                continue
            try:
                found[name] = Entry(kind, ep, _make_spec(kind, name, data), family)
            except BenchError as exc:
                broken[name] = str(exc)
    return dict(sorted(found.items())), broken


def _warn(kind: Kind, broken: dict[str, str]) -> None:
    for name, reason in broken.items():
        warnings.warn(f"skipping {kind[:-1]} {name!r}: {reason}", PluginWarning, stacklevel=3)


def entries(kind: Kind) -> dict[str, Entry]:
    """All usable registered variants of `kind`, by name; unusable ones are reported as warnings."""
    found, broken = _scan(kind)
    _warn(kind, broken)
    return found


def get(kind: Kind, name: str) -> Entry:
    """The registered variant `name`, or a one-line error with suggestions. Asking for a registered
    variant that cannot be used is that one-line error (other unusable ones are warnings)."""
    found, broken = _scan(kind)
    reason = broken.pop(name, None)
    _warn(kind, broken)
    if reason is not None:
        raise SpecError(f"{kind[:-1]} {name!r} cannot be used: {reason}")
    if name not in found:
        raise SpecError(did_you_mean(kind[:-1], name, list(found)))
    return found[name]


def describe(kind: Kind) -> list[dict[str, Any]]:
    """Rows for `mftcn-bench list`: name, the distribution that ships it and one-line description. Each
    implementation is imported, so an entry point naming a missing class or a module that fails to import
    is reported (a warning) and left out, as a package without its spec file is."""
    rows = []
    for entry in entries(kind).values():
        try:
            entry.load()
        except BenchError as exc:
            warnings.warn(f"skipping {kind[:-1]} {entry.name!r}: {exc}", PluginWarning, stacklevel=2)
            continue
        dist = entry.registered_by.dist
        shipped = f"{dist.metadata['Name']} {dist.version}" if dist is not None else "-"
        rows.append({"name": entry.name, "from": shipped, "description": entry.description})
    return rows
