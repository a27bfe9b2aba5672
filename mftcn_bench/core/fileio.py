"""Crash- and concurrency-safe file writing: atomic replacement and an exclusive inter-process lock."""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a temporary file beside `path`, flush to disk, then rename over it."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def resume_folder(root: Path) -> dict[str, dict[str, Any]]:
    """Make `root` ready for a resumable build whose lock the caller holds: create it, delete writes that a
    kill cut off (never read), and return what `root/progress.json` says was finished, by file name."""
    root.mkdir(parents=True, exist_ok=True)
    for stale in root.glob(".*.tmp-*"):
        stale.unlink()
    progress_path = root / "progress.json"
    if not progress_path.exists():
        return {}
    return {entry["file"]: entry for entry in json.loads(progress_path.read_text())}


@contextmanager
def exclusive_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on `path` (created if needed) so that concurrent processes build a shared
    thing (a dataset, a trained encoder) once: the others wait, then find it built."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
