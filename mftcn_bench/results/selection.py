"""Which stored runs a table, leaderboard or plot counts.

A run counts when it was made with today's spec files for its encoder, task and preset, with at most the
keys a table varies overridden (`VARIED`: the embedding size, which the paper's tables vary; the PPO-limit
analyses also vary PPO's budget): runs of older specs or other overrides are never mixed in. Of several
such runs of one variant (encoder, task, preset, the varied keys' values), only those of one code and one data
set count: the runs sharing the encoder's and the task's code identities and the data set's fingerprint with
the variant's latest run (so a row never mixes two versions of an encoder or two recordings of its data), and
of those the latest per seed.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from mftcn_bench.core import registry
from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.specs import resolve_config
from mftcn_bench.results.store import RunRecord

Accept = Callable[[RunRecord], bool]

VARIED: tuple[str, ...] = ("encoder.embedding_dim",)  # what a table varies between rows unless it says more

# The presets a table shows when none is named, in the order its rows show them: the paper's protocol, then
# the quick budget. Others (smoke, demo) check the machinery on toy data and are shown only when named.
TABLE_PRESETS: tuple[str, ...] = ("paper", "quick")


def preset_order(preset: str) -> tuple[int, str]:
    """Sort key of a preset: the table presets in their order, then the others by name."""
    return (TABLE_PRESETS.index(preset) if preset in TABLE_PRESETS else len(TABLE_PRESETS), preset)


def exclusion(record: RunRecord, varied: Sequence[str] = VARIED) -> str | None:
    """Why a stored run does not count for today's specs with the `varied` keys as the run had them (None:
    it counts)."""
    try:
        encoder, task = registry.get("encoders", record.encoder), registry.get("tasks", record.task)
    except BenchError:
        return "encoder or task not installed here"
    overrides = [(key, value) for key in varied if (value := config_value(record, key)) is not None]
    try:
        _, config = resolve_config(encoder.spec, task.spec, record.preset, overrides)
    except (BenchError, KeyError, TypeError):
        return "a config today's specs cannot reproduce"
    if (_without_diagnostics(config["encoder"]) != _without_diagnostics(record.config.get("encoder"))
            or config["task"] != record.config.get("task")):
        return "older spec files or other overrides"
    return None


# Encoder spec keys that only add diagnostics to a record and change no fitted weight (tests/test_mftcn.py
# holds the fit to that): a run recorded before they existed, or with other values, still counts.
DIAGNOSTIC_KEYS: tuple[str, ...] = ("train.heldout_every", "train.heldout_batches")
# Encoder spec keys added later with the value that computes what the runs before them computed (the
# paper's head; tests/test_mftcn.py): a run recorded without the key counts as having that value.
ADDED_KEYS: dict[str, Any] = {"model.temporal_kernel": 3, "model.spatial_pool": "mean"}


def _without_diagnostics(encoder: Any) -> Any:
    """The encoder config as runs are compared: diagnostic keys dropped, added keys at their value."""
    if not isinstance(encoder, Mapping):
        return encoder
    tables = {name: dict(table) for name, table in encoder.items() if isinstance(table, Mapping)}
    for key in DIAGNOSTIC_KEYS:
        table, leaf = key.split(".")
        tables.get(table, {}).pop(leaf, None)
    for key, value in ADDED_KEYS.items():
        table, leaf = key.split(".")
        if table in tables:
            tables[table].setdefault(leaf, value)
    return {**encoder, **tables}


def matches_current_specs(record: RunRecord) -> bool:
    """Whether a stored run used today's spec files for its encoder, task and preset, with at most the
    embedding size overridden."""
    return exclusion(record) is None


def current_specs_varying(varied: Sequence[str]) -> Accept:
    """Accept the runs of today's spec files with at most the `varied` keys overridden."""
    if tuple(varied) == VARIED:
        return matches_current_specs
    return lambda record: exclusion(record, varied) is None


def left_out(records: Iterable[RunRecord], accept: Accept = matches_current_specs,
             varied: Sequence[str] = VARIED) -> dict[str, int]:
    """How many of `records` `counted_runs` leaves out, by reason."""
    return dict(sorted(_select(records, accept, varied)[1].items()))


def left_out_line(records: Iterable[RunRecord], accept: Accept = matches_current_specs,
                  varied: Sequence[str] = VARIED) -> str | None:
    """`Left out: 3 stored runs (2 older spec files ..., 1 ...).`, or None when every run counts."""
    reasons = left_out(records, accept, varied)
    if not reasons:
        return None
    total = sum(reasons.values())
    return (f"Left out: {total} stored run{'s' if total > 1 else ''} ("
            + "; ".join(f"{n}: {why}" for why, n in reasons.items()) + ").")


ROW_PARTS: tuple[str, ...] = ("encoder code", "task code", "data set")


def row_key(record: RunRecord) -> tuple[str, str, str]:
    """What the runs of one table row share: the encoder's and the task's code identities (`code.*` of the
    record, without `editable`) and the data set's fingerprint. Runs recorded before code identities have
    '-' for them."""
    def code(part: str) -> str:
        found = config_value(record, f"code.{part}")
        if not isinstance(found, Mapping):
            return "-"
        return "/".join(str(found.get(k)) for k in ("module", "distribution", "version", "source"))

    return code("encoder"), code("task"), record.dataset_id or "-"


def _select(records: Iterable[RunRecord], accept: Accept,
            varied: Sequence[str]) -> tuple[list[RunRecord], Counter[str]]:
    """(the counted runs, why each other run is left out). Of a variant's accepted runs only the latest group
    of one `row_key` counts (the group holding the variant's latest run), the latest run per seed in it."""
    reasons: Counter[str] = Counter()
    variants: dict[tuple, list[RunRecord]] = {}
    for record in records:
        if accept(record):
            variants.setdefault(variant_key(record, varied), []).append(record)
        else:
            reasons[exclusion(record, varied) or "not selected"] += 1
    counted: list[RunRecord] = []
    for runs in variants.values():
        newest = max(runs, key=_when)
        row = row_key(newest)
        latest: dict[int, RunRecord] = {}
        for record in runs:
            other = row_key(record)
            if other != row:
                differs = ", ".join(p for p, a, b in zip(ROW_PARTS, other, row, strict=True) if a != b)
                reasons[f"a different {differs} from the row's latest runs"] += 1
                continue
            kept = latest.get(record.seed)
            if kept is None or _when(record) > _when(kept):
                if kept is not None:
                    reasons["a later run of the same seed counts instead"] += 1
                latest[record.seed] = record
            else:
                reasons["a later run of the same seed counts instead"] += 1
        counted += latest.values()
    return sorted(counted, key=lambda r: (tuple(str(p) for p in variant_key(r, varied)), r.seed)), reasons


def shared_dataset(runs: Iterable[RunRecord]) -> str | None:
    """The data set that runs of different encoders on one (task, preset) are compared on: the one most of the
    runs that read data read (a tie: the latest run's of the tied ones); None when none reads data. Each row reads
    one data set, but rows can rest on different recordings (another machine, another collector's code)."""
    reading = [r for r in runs if r.dataset_id]
    if not reading:
        return None
    counts = Counter(r.dataset_id for r in reading)
    return max(reading, key=lambda r: (counts[r.dataset_id], _when(r))).dataset_id


def other_dataset_note(marked: str) -> str:
    """The one explanation of a `*` that boards, tables and the scorecard put beside what `shared_dataset` marks;
    `marked` names what carries the mark ("Entries", "Seeds", "Cells")."""
    return (f"{marked} marked * rest on another recording of the task's data (another machine or collector code) than "
            "most of the task's runs read; they compare with the rest only as far as the recordings agree.")


def _when(record: RunRecord) -> tuple[str, str]:
    return record.created_at, record.run_id


def code_label(record: RunRecord) -> str:
    """The encoder's code as recorded: `my-plugin 0.2.0` for a plugin, `mftcn-bench 0.1.0` for a built-in
    (runs recorded before code identities name the harness's version)."""
    code = config_value(record, "code.encoder")
    if isinstance(code, dict) and code.get("distribution"):
        return f"{code['distribution']} {code.get('version') or '?'}"
    return f"mftcn-bench {record.versions.get('mftcn-bench', '?')}"


def config_value(record: RunRecord, dotted: str) -> Any:
    """A value of the run's resolved config by dotted key (`encoder.embedding_dim`); None if absent."""
    return lookup(record.config, dotted)


def lookup(config: Mapping[str, Any], dotted: str) -> Any:
    """A value of a resolved config (`{"encoder": ..., "task": ...}`) by dotted key; None if absent."""
    node: Any = config
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


class SpecDefaults:
    """The config a run's encoder, task and preset resolve to today without overrides, one resolution per
    (encoder, task, preset): what a table compares each run's varied keys with."""

    def __init__(self) -> None:
        self._configs: dict[tuple[str, str, str | None], dict[str, Any] | None] = {}

    def __call__(self, record: RunRecord) -> dict[str, Any] | None:
        key = (record.encoder, record.task, record.preset)
        if key not in self._configs:
            try:
                encoder, task = registry.get("encoders", record.encoder), registry.get("tasks", record.task)
                self._configs[key] = resolve_config(encoder.spec, task.spec, record.preset)[1]
            except (BenchError, KeyError, TypeError):
                self._configs[key] = None
        return self._configs[key]


def overridden(record: RunRecord, varied: Sequence[str] = VARIED) -> dict[str, Any]:
    """The `varied` keys whose value in the run is not the one today's specs give without overrides."""
    default = SpecDefaults()(record)
    if default is None:
        return {}
    return {key: value for key in varied
            if (value := config_value(record, key)) is not None and value != lookup(default, key)}


def variant_key(record: RunRecord, varied: Sequence[str] = VARIED) -> tuple[Any, ...]:
    """(encoder, task, preset, the varied keys' values): runs of one variant differ only by seed."""
    return (record.encoder, record.task, record.preset, *(config_value(record, key) for key in varied))


def counted_runs(records: Iterable[RunRecord], accept: Accept = matches_current_specs,
                 varied: Sequence[str] = VARIED) -> list[RunRecord]:
    """The accepted runs of each variant's latest row (one encoder code, one task code, one data set:
    `row_key`), the latest per seed, ordered by variant then seed."""
    return _select(records, accept, varied)[0]


def variant_label(record: RunRecord, varied: Sequence[str] = VARIED) -> str:
    """The encoder's name, with those of the `varied` keys that were overridden: `mftcn4 (embedding 8)`,
    `mftcn4 (model.base.name=small-cnn)`."""
    parts = [f"embedding {value}" if key == "encoder.embedding_dim" else f"{key.removeprefix('encoder.')}={value}"
             for key, value in overridden(record, varied).items()]
    return f"{record.encoder} ({', '.join(parts)})" if parts else record.encoder
