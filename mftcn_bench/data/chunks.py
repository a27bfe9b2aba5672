"""Chunk files: one episode's arrays in a deterministic, compressed .npz, written atomically.

`numpy.savez_compressed` stamps the current time into the zip, so the same data would give different
bytes; this writes the same container with a fixed timestamp, so the same seed gives the same checksum.
Readers use plain `numpy.load` (pickles refused).
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mftcn_bench.core.errors import DataError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.provenance import file_sha256

FIXED_TIME = (1980, 1, 1, 0, 0, 0)


def write_chunk(path: Path, arrays: Mapping[str, np.ndarray], compresslevel: int = 6) -> str:
    """Write `arrays` to `path` atomically; returns the file's sha256."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=compresslevel) as zf:
        for name in sorted(arrays):
            npy = io.BytesIO()
            np.lib.format.write_array(npy, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=FIXED_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, npy.getvalue(), compresslevel=compresslevel)
    atomic_write_bytes(path, buffer.getvalue())
    return file_sha256(path)


def read_chunk(path: Path, sha256: str | None = None) -> dict[str, np.ndarray]:
    """All arrays of a chunk; with `sha256`, the file is checked first."""
    if not path.exists():
        raise DataError(f"dataset chunk {path} is missing; delete the dataset folder to collect it again")
    if sha256 is not None and file_sha256(path) != sha256:
        raise DataError(f"dataset chunk {path} does not match its checksum in the manifest; "
                        f"delete the dataset folder {path.parent} to collect it again")
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError) as exc:
        raise DataError(f"dataset chunk {path} cannot be read ({exc})") from None
