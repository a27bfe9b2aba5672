"""Repack a wheel without some of its folders: the dm-control wheel (56 MB, Apache-2.0) without the
locomotion, dog and test assets that `dm_control.suite`'s cartpole and cheetah never read, so that it fits
the 64 MiB a device call may carry (`scripts/device-check.sh prepare`).

Own code because no packaging tool subsets a wheel; the RECORD is rewritten with the kept files' hashes,
so pip installs the result like any wheel.

    python scripts/slim_wheel.py IN.whl OUT_DIR PREFIX [PREFIX ...]
"""

from __future__ import annotations

import base64
import hashlib
import sys
import zipfile
from pathlib import Path


def _record_line(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"


def slim(wheel: Path, out_dir: Path, drop: list[str]) -> Path:
    """Write `out_dir/<same name>` holding every file of `wheel` except those under a prefix in `drop` and
    test modules (`*_test.py`); returns its path."""
    out = out_dir / wheel.name
    with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as target:
        record_name = next(n for n in source.namelist() if n.endswith(".dist-info/RECORD"))
        lines = []
        for info in source.infolist():
            name = info.filename
            if name == record_name or any(name.startswith(p) for p in drop) or name.endswith("_test.py"):
                continue
            data = source.read(info)
            target.writestr(info, data)
            lines.append(_record_line(name, data))
        target.writestr(record_name, "\n".join([*lines, f"{record_name},,"]) + "\n")
    return out


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__.strip().splitlines()[-1].strip())
    path = slim(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:])
    print(f"{path}: {path.stat().st_size / 1e6:.1f} MB")
