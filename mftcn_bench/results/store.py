"""The results store: one SQLite database, one row per finished run, written in one transaction.

A row exists only for a run that finished, so a run killed at any moment leaves no half-written result.
WAL mode and a busy timeout let a sweep's worker processes write concurrently.
"""

from __future__ import annotations

import json
import os
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mftcn_bench.core.errors import BenchError

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id      TEXT PRIMARY KEY,
    encoder     TEXT NOT NULL,
    task        TEXT NOT NULL,
    preset      TEXT NOT NULL,
    seed        INTEGER NOT NULL,
    dataset_id  TEXT,
    config      TEXT NOT NULL,
    versions    TEXT NOT NULL,
    metrics     TEXT NOT NULL,
    timings     TEXT NOT NULL,
    artifacts   TEXT,
    created_at  TEXT NOT NULL,
    curves      TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX IF NOT EXISTS runs_by_task ON runs (task, encoder, preset);
"""


@dataclass(frozen=True)
class RunRecord:
    """A finished run as stored: identity, full resolved config, versions, metrics, timings."""

    run_id: str
    encoder: str
    task: str
    preset: str
    seed: int
    dataset_id: str | None
    config: dict[str, Any]
    versions: dict[str, Any]
    metrics: dict[str, Any]
    timings: dict[str, float]
    artifacts: str | None = None
    created_at: str = ""
    curves: dict[str, dict[str, list[float]]] = field(default_factory=dict)


class ResultStore:
    """Read and write finished runs in the SQLite database at `path`."""

    def __init__(self, path: Path, busy_timeout_s: float = 60.0) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._busy_timeout_s = busy_timeout_s
        with self._connect() as conn:
            conn.execute("PRAGMA journal_mode=WAL")
            conn.executescript(SCHEMA)
            columns = {row[1] for row in conn.execute("PRAGMA table_info(runs)")}
            if "curves" not in columns:  # a store written before curves were kept
                conn.execute("ALTER TABLE runs ADD COLUMN curves TEXT NOT NULL DEFAULT '{}'")

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        try:
            conn = sqlite3.connect(self.path, timeout=self._busy_timeout_s)
            try:
                conn.execute(f"PRAGMA busy_timeout={int(self._busy_timeout_s * 1000)}")
                with conn:  # one transaction: committed on success, rolled back on error
                    yield conn
            finally:
                conn.close()
        except sqlite3.DatabaseError as exc:  # not a database, read-only, disk full: one line, not a traceback
            raise BenchError(f"results database {self.path} cannot be used ({exc}); move it away to start a "
                             f"new one, or choose another results folder with --home") from None

    def check_writable(self) -> None:
        """Refuse a read-only database before a run does its work, rather than when it stores the result."""
        for target in (self.path.parent, self.path):
            if target.exists() and not os.access(target, os.W_OK):
                raise BenchError(f"results database {self.path} is read-only ({target} is not writable); "
                                 f"make it writable or choose another results folder with --home")

    def put(self, record: RunRecord) -> None:
        """Insert or replace (after --force) one finished run, atomically."""
        created = record.created_at or datetime.now(UTC).isoformat(timespec="seconds")
        with self._connect() as conn:
            conn.execute(
                "INSERT OR REPLACE INTO runs VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (
                    record.run_id, record.encoder, record.task, record.preset, record.seed,
                    record.dataset_id, json.dumps(record.config, sort_keys=True),
                    json.dumps(record.versions, sort_keys=True), json.dumps(record.metrics, sort_keys=True),
                    json.dumps(record.timings, sort_keys=True), record.artifacts, created,
                    json.dumps(record.curves, sort_keys=True),
                ),
            )

    def get(self, run_id: str) -> RunRecord | None:
        with self._connect() as conn:
            row = conn.execute("SELECT * FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        return _record(row) if row else None

    def query(self, task: str | None = None, encoder: str | None = None,
              preset: str | None = None) -> list[RunRecord]:
        """Finished runs matching every given field, oldest first."""
        clauses, args = [], []
        for column, value in (("task", task), ("encoder", encoder), ("preset", preset)):
            if value is not None:
                clauses.append(f"{column} = ?")
                args.append(value)
        where = f"WHERE {' AND '.join(clauses)}" if clauses else ""
        with self._connect() as conn:
            rows = conn.execute(f"SELECT * FROM runs {where} ORDER BY created_at, run_id", args).fetchall()
        return [_record(row) for row in rows]

    def integrity_ok(self) -> bool:
        with self._connect() as conn:
            return conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def _record(row: tuple) -> RunRecord:
    (run_id, encoder, task, preset, seed, dataset_id, config, versions, metrics, timings, artifacts,
     created_at, curves) = row
    return RunRecord(run_id, encoder, task, preset, int(seed), dataset_id, json.loads(config),
                     json.loads(versions), json.loads(metrics), json.loads(timings), artifacts, created_at,
                     json.loads(curves))
