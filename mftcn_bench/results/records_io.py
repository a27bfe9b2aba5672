"""Results as files: export one JSON file per run, import such files into a store.

This is how results travel: contributed by pull request, or gathered from many machines into one store.
A file holds the whole RunRecord (identity, resolved config, versions, metrics, curves, timings,
created_at); its name is the run id. Import checks every file before writing anything, and is
idempotent: a run already stored is kept unless the file holds a later one (a rerun with --force).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.results.store import ResultStore, RunRecord


class ResultsFileError(BenchError):
    """A results file that cannot be imported."""


@dataclass(frozen=True)
class ImportSummary:
    added: int
    updated: int
    unchanged: int


_TYPES: dict[str, type | tuple[type, ...]] = {
    "run_id": str, "encoder": str, "task": str, "preset": str, "seed": int, "dataset_id": (str, type(None)),
    "config": dict, "versions": dict, "metrics": dict, "timings": dict, "artifacts": (str, type(None)),
    "created_at": str, "curves": dict,
}
_OPTIONAL = {"artifacts": None, "curves": {}}


def record_to_json(record: RunRecord) -> bytes:
    return json.dumps(asdict(record), indent=1, sort_keys=True).encode()


def record_from_json(data: Any, origin: str) -> RunRecord:
    """A RunRecord from parsed JSON, or a one-line error naming `origin` and what is wrong."""
    if not isinstance(data, dict):
        raise ResultsFileError(f"results file {origin}: expected a JSON object (a run record)")
    names = [f.name for f in fields(RunRecord)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ResultsFileError(f"results file {origin}: unknown fields {unknown}")
    values = {**_OPTIONAL, **data}
    for name in names:
        if name not in values:
            raise ResultsFileError(f"results file {origin}: missing field {name!r}")
        expected = _TYPES[name]
        value = values[name]
        if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            raise ResultsFileError(f"results file {origin}: field {name!r} has the wrong type "
                                   f"({type(value).__name__})")
    if not values["run_id"] or not values["created_at"] or values["seed"] < 0:
        raise ResultsFileError(f"results file {origin}: run_id and created_at must be set and seed >= 0")
    return RunRecord(**{name: values[name] for name in names})


def export_results(store: ResultStore, out: Path, task: str | None = None, preset: str | None = None) -> int:
    """Write `<run id>.json` under `out` for every stored run (of `task`/`preset` if given)."""
    out.mkdir(parents=True, exist_ok=True)
    records = store.query(task=task, preset=preset)
    for record in records:
        atomic_write_bytes(out / f"{record.run_id}.json", record_to_json(record))
    return len(records)


def read_results(folder: Path) -> list[RunRecord]:
    """Every `*.json` run record in `folder`, all checked; the first bad file stops it with its name."""
    if not folder.is_dir():
        raise ResultsFileError(f"{folder} is not a folder of results files")
    records = []
    for path in sorted(folder.glob("*.json")):
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ResultsFileError(f"results file {path}: not readable JSON ({exc})") from None
        records.append(record_from_json(data, str(path)))
    return records


def import_results(store: ResultStore, folder: Path) -> ImportSummary:
    """Merge the run records in `folder` into `store`; nothing is written if any file is bad."""
    records = read_results(folder)
    added = updated = unchanged = 0
    for record in records:
        existing = store.get(record.run_id)
        if existing is None:
            added += 1
        elif existing.created_at < record.created_at:
            updated += 1
        else:
            unchanged += 1
            continue
        store.put(record)
    return ImportSummary(added, updated, unchanged)
