"""Spec files (TOML, parsed as data) and their resolution into one run configuration.

A run's configuration is `{"encoder": <encoder spec>, "task": <task spec without presets>}`. A task's
preset (`[presets.<name>]` in its spec) and the command line's `--set key=value` overrides are applied to
it in that order, as dotted keys rooted at `encoder.` or `task.`. Overrides may only change keys that the
spec already has, with a value of the same type, so a typo never silently runs the default.
"""

from __future__ import annotations

import copy
import json
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

from mftcn_bench.core.errors import SpecError, did_you_mean


@dataclass(frozen=True)
class EncoderSpec:
    """An encoder variant: family, clip shape (frames n at stride s), embedding size, and free-form
    `model` and `train` tables that the family's implementation validates."""

    name: str
    family: str
    description: str
    frames: int = 1
    stride: int = 1
    embedding_dim: int = 32
    model: Mapping[str, Any] = field(default_factory=dict)
    train: Mapping[str, Any] = field(default_factory=dict)

    @property
    def lookback(self) -> int:
        """Frames spanned by one clip: (n - 1) * s + 1."""
        return (self.frames - 1) * self.stride + 1

    @classmethod
    def from_dict(cls, name: str, data: Mapping[str, Any]) -> EncoderSpec:
        known = {"family", "description", "frames", "stride", "embedding_dim", "model", "train"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise SpecError(f"encoder spec {name!r}: unknown keys {unknown}; allowed: {sorted(known)}")
        for key in ("family", "description"):
            if not isinstance(data.get(key), str):
                raise SpecError(f"encoder spec {name!r}: {key!r} must be a string")
        spec = cls(
            name=name,
            family=data["family"],
            description=data["description"],
            frames=int(data.get("frames", 1)),
            stride=int(data.get("stride", 1)),
            embedding_dim=int(data.get("embedding_dim", 32)),
            model=dict(data.get("model", {})),
            train=dict(data.get("train", {})),
        )
        for key in ("frames", "stride", "embedding_dim"):
            if getattr(spec, key) < 1:
                raise SpecError(f"encoder spec {name!r}: {key} must be >= 1, got {getattr(spec, key)}")
        return spec


@dataclass(frozen=True)
class TaskSpec:
    """A task variant: its description, its tables (dataset, protocol numbers), its presets and its
    optional `[leaderboard]` table (metric, higher_is_better, label): how results are ranked, which is not
    part of a run's config, so it never changes a run's id."""

    name: str
    description: str
    default_preset: str
    tables: Mapping[str, Any]
    presets: Mapping[str, Mapping[str, Any]]
    leaderboard: Mapping[str, Any] = field(default_factory=dict)
    # `[encoder_defaults.<encoder>]`: what this task sets for one encoder before presets and overrides,
    # e.g. the state size of true-state and random-state on a domain whose state is not cartpole's. A preset
    # may have its own `[presets.<preset>.encoder_defaults.<encoder>]`, applied after the preset's other keys
    # (e.g. fewer clips a batch for a long lookback on a preset with short episodes).
    encoder_defaults: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, name: str, data: Mapping[str, Any]) -> TaskSpec:
        data = dict(data)
        presets = data.pop("presets", {})
        encoder_defaults = data.pop("encoder_defaults", {})
        if not _tables_of_tables(encoder_defaults):
            raise SpecError(f"task spec {name!r}: [encoder_defaults.<encoder>] must be tables")
        for preset_name, preset in presets.items():
            if not isinstance(preset, Mapping) or not _tables_of_tables(preset.get("encoder_defaults", {})):
                raise SpecError(f"task spec {name!r}: [presets.{preset_name}.encoder_defaults.<encoder>] "
                                "must be tables")
        description = data.pop("description", None)
        default_preset = data.pop("default_preset", None)
        leaderboard = data.pop("leaderboard", {})
        if not isinstance(leaderboard, Mapping) or not isinstance(leaderboard.get("metric", ""), str):
            raise SpecError(f"task spec {name!r}: [leaderboard] must be a table with a string 'metric'")
        if not isinstance(description, str):
            raise SpecError(f"task spec {name!r}: 'description' must be a string")
        if not presets or default_preset not in presets:
            raise SpecError(f"task spec {name!r}: 'default_preset' must name one of its [presets.*] tables")
        return cls(name, description, default_preset, data, presets, dict(leaderboard),
                   {k: dict(v) for k, v in encoder_defaults.items()})


def _tables_of_tables(value: Any) -> bool:
    return isinstance(value, Mapping) and all(isinstance(v, Mapping) for v in value.values())


def parse_toml(text: str, origin: str) -> dict[str, Any]:
    """Parse spec text as data (never evaluated); errors name the file."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"spec file {origin}: not valid TOML ({exc})") from None


def merge_tables(base: Mapping[str, Any], child: Mapping[str, Any]) -> dict[str, Any]:
    """`child` over `base`: tables merge key by key (recursively), any other value replaces."""
    out = dict(base)
    for key, value in child.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge_tables(out[key], value)
        else:
            out[key] = value
    return out


def load_spec_tree(kind: str, name: str, read: Callable[[str, str], str], origin: str,
                   seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """A spec file as data, with its templates and dataset resolved: `extends = "<spec>"` merges this file
    over that spec of the same kind (recursively; `_name` files are templates, never variants); a table's
    `same_as = "<spec>.<table>"` (or `"<table>"` of this spec) stands for that table with this table's other
    keys over it (imitate-swingup's expert is swingup's [ppo] with another budget); and in a task spec
    `dataset = "<name>"` stands for the table of `specs/datasets/<name>.toml`, over which this file's
    `[dataset.*]` keys of an extending spec then merge. `read(folder, name)` returns a file's text."""
    data = _load_extended(kind, name, read, origin, seen)
    return {key: _resolve_same_as(kind, name, key, data, read, origin, (*seen, name)) for key in data}


def _load_extended(kind: str, name: str, read: Callable[[str, str], str], origin: str,
                   seen: tuple[str, ...]) -> dict[str, Any]:
    if name in seen:
        raise SpecError(f"spec {origin}/{kind}/{name}.toml: `extends` loops ({' -> '.join((*seen, name))})")
    data = parse_toml(read(kind, name), f"{origin}/{kind}/{name}.toml")
    if isinstance(data.get("dataset"), str):
        reference = data["dataset"]
        data["dataset"] = parse_toml(read("datasets", reference), f"{origin}/datasets/{reference}.toml")
    parent = data.pop("extends", None)
    if parent is None:
        return data
    if not isinstance(parent, str):
        raise SpecError(f"spec {origin}/{kind}/{name}.toml: extends must be a spec name, got {parent!r}")
    return merge_tables(_load_extended(kind, parent, read, origin, (*seen, name)), data)


def _resolve_same_as(kind: str, name: str, key: str, data: Mapping[str, Any], read: Callable[[str, str], str],
                     origin: str, seen: tuple[str, ...], chain: tuple[str, ...] = ()) -> Any:
    """Table `key` of spec `name` (`data`, extends resolved) with its `same_as` reference replaced by the
    table it names, this table's other keys over it; any other value as it is. `seen`: the specs being
    loaded, `chain`: this spec's tables being resolved (both to refuse a loop)."""
    table = data[key]
    if not isinstance(table, Mapping) or "same_as" not in table:
        return table
    where = f"spec {origin}/{kind}/{name}.toml: [{key}] same_as"
    reference = table["same_as"]
    if not isinstance(reference, str) or not reference or reference.count(".") > 1:
        raise SpecError(f"{where} must be \"<spec>.<table>\" or \"<table>\" of this spec, got {reference!r}")
    spec, _, other = reference.rpartition(".")
    if (spec in seen) if spec else (other in (*chain, key)):
        raise SpecError(f"{where} = {reference!r} loops ({' -> '.join((*(seen if spec else chain), key, reference))})")
    source = load_spec_tree(kind, spec, read, origin, seen) if spec else data
    if not isinstance(source.get(other), Mapping):
        tables = sorted(k for k, v in source.items() if isinstance(v, Mapping))
        raise SpecError(f"{where} = {reference!r} names no table of spec {spec or name!r}; its tables: {tables}")
    resolved = (source[other] if spec
                else _resolve_same_as(kind, name, other, data, read, origin, seen, (*chain, key)))
    return merge_tables(resolved, {k: v for k, v in table.items() if k != "same_as"})


def flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """{'a': {'b': 1}} -> {'a.b': 1}. Lists and scalars are leaves."""
    out: dict[str, Any] = {}
    for key, value in table.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{path}."))
        else:
            out[path] = value
    return out


def parse_override(text: str) -> tuple[str, Any]:
    """`encoder.embedding_dim=8` -> ('encoder.embedding_dim', 8). Values are TOML literals; a bare word
    that is not one is taken as a string."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise SpecError(f"override {text!r} is not KEY=VALUE (for example encoder.embedding_dim=8)")
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key, value


def _type_name(value: Any) -> str:
    return {bool: "bool", int: "int", float: "float", str: "string", list: "list"}.get(type(value), "table")


def _coerce(key: str, old: Any, new: Any) -> Any:
    """The new value if it has the old value's type (an int is accepted where a float was)."""
    if isinstance(old, bool) or isinstance(new, bool):
        if isinstance(old, bool) and isinstance(new, bool):
            return new
    elif isinstance(old, float) and isinstance(new, int | float):
        return float(new)
    elif type(old) is type(new):
        return new
    raise SpecError(f"override {key}={json.dumps(new)}: expected a {_type_name(old)} like {json.dumps(old)}")


def apply_overrides(
    config: dict[str, Any], overrides: Iterable[tuple[str, Any]], *, skip_missing_encoder_keys: bool = False
) -> dict[str, Any]:
    """A copy of `config` with each dotted key set. Keys must exist already (presets may name encoder
    keys that a given encoder family lacks: those are skipped when `skip_missing_encoder_keys`)."""
    config = copy.deepcopy(config)
    valid = sorted(flatten(config))
    for key, value in overrides:
        parts = key.split(".")
        node: Any = config
        for i, part in enumerate(parts):
            if not isinstance(node, dict) or part not in node:
                if skip_missing_encoder_keys and parts[0] == "encoder":
                    break
                raise SpecError(did_you_mean("override key", key, valid))
            if i == len(parts) - 1:
                if isinstance(node[part], dict):
                    raise SpecError(f"override key {key!r} names a table; set one of its keys instead")
                node[part] = _coerce(key, node[part], value)
            else:
                node = node[part]
    return config


def resolve_config(
    encoder: EncoderSpec, task: TaskSpec, preset: str | None, overrides: Iterable[tuple[str, Any]] = ()
) -> tuple[str, dict[str, Any]]:
    """(preset name, resolved config) for this encoder on this task."""
    preset = preset or task.default_preset
    if preset not in task.presets:
        raise SpecError(did_you_mean(f"preset of task {task.name!r}:", preset, list(task.presets)))
    config = {
        "encoder": {
            "name": encoder.name,
            "family": encoder.family,
            "frames": encoder.frames,
            "stride": encoder.stride,
            "embedding_dim": encoder.embedding_dim,
            "model": dict(encoder.model),
            "train": dict(encoder.train),
        },
        "task": {"name": task.name, **copy.deepcopy(dict(task.tables))},
    }
    defaults = task.encoder_defaults.get(encoder.name, {})
    config = apply_overrides(config, flatten(defaults, "encoder.").items())
    preset_table = dict(task.presets[preset])
    preset_encoder_defaults = preset_table.pop("encoder_defaults", {}).get(encoder.name, {})
    config = apply_overrides(config, flatten(preset_table).items(), skip_missing_encoder_keys=True)
    config = apply_overrides(config, flatten(preset_encoder_defaults, "encoder.").items())
    overrides = list(overrides)
    for key, _ in overrides:
        if key in ("encoder.name", "encoder.family", "task.name"):
            raise SpecError(f"override key {key!r} cannot be changed; choose another --encoder/--task")
    return preset, apply_overrides(config, overrides)


def encoder_spec_from_config(description: str, config: Mapping[str, Any]) -> EncoderSpec:
    """The EncoderSpec that a resolved config's `encoder` table describes."""
    enc = dict(config)
    name = enc.pop("name")
    spec = EncoderSpec.from_dict(name, {**enc, "description": description})
    return spec


T = TypeVar("T")


def parse_table(cls: type[T], owner: str, section: str, table: Mapping[str, Any]) -> T:
    """The dataclass `cls` from a spec table; unknown, missing or ill-typed keys are a one-line SpecError
    naming `owner` (`encoder 'mftcn4'`, `task 'swingup'`) and the `[section]`."""
    known = [f.name for f in fields(cls)]  # type: ignore[arg-type] - cls is a dataclass
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise SpecError(f"{owner}: bad [{section}] table: unknown key(s) {unknown}; allowed: {sorted(known)}")
    try:
        return cls(**dict(table))
    except TypeError as exc:
        raise SpecError(f"{owner}: bad [{section}] table ({exc})") from None
