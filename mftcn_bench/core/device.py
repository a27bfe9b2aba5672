"""Which device a run computes on: `--device auto|cpu|cuda[:N]` (or `MFTCN_BENCH_DEVICE`), checked before
any work, and the capability by which encoders and tasks are placed on it.

`auto` is CUDA when torch sees a GPU, else the CPU. A run records its `Placement` (device, GPU name, CUDA
and cuDNN versions, whether deterministic algorithms were asked for) and, off the CPU, its identity holds
the part that can change a number: the GPU's name, the CUDA version and the determinism flag (`cuda:0`
and `cuda:1` of one machine are the same identity); a CPU placement adds nothing to an identity.
Environments always step on the CPU; what is placed is the networks: encoder training and embedding, the
feature cache's base passes, PPO.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from mftcn_bench.core.errors import BenchError

if TYPE_CHECKING:  # torch is imported where it is used: the command line parses flags without it
    import torch

ENV_VAR = "MFTCN_BENCH_DEVICE"
CHOICES = "auto, cpu, cuda or cuda:N"
_PATTERN = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


@dataclass(frozen=True)
class Placement:
    """The resolved device of a run and what it records about it."""

    device: str                 # "cpu" or "cuda:N"
    gpu: str | None = None      # torch.cuda.get_device_name
    cuda: str | None = None     # torch.version.cuda
    cudnn: int | None = None    # torch.backends.cudnn.version()
    deterministic: bool = False

    @property
    def torch_device(self) -> torch.device:
        import torch

        return torch.device(self.device)

    @property
    def is_cuda(self) -> bool:
        return self.device.startswith("cuda")

    def record(self) -> dict[str, Any]:
        """What a run record keeps under `config.device`."""
        return asdict(self)

    def identity(self) -> dict[str, Any]:
        """What of the placement can change a result (part of run ids and encoder keys)."""
        if not self.is_cuda:
            return {"device": "cpu"}
        return {"device": "cuda", "gpu": self.gpu, "cuda": self.cuda, "deterministic": self.deterministic}


CPU = Placement("cpu")


def requested_device(flag: str | None) -> str:
    """The flag's value, else `MFTCN_BENCH_DEVICE`, else "auto"."""
    return flag or os.environ.get(ENV_VAR) or "auto"


def resolve_device(name: str, deterministic: bool = False) -> Placement:
    """`name` -> a Placement on this machine; an unknown name, or CUDA where torch sees none, is a one-line
    `BenchError` (exit 2) before any work."""
    text = name.strip().lower()
    if not _PATTERN.match(text):
        raise BenchError(f"unknown device {name!r}; allowed: {CHOICES}")
    import torch

    available = torch.cuda.is_available()
    if text == "auto":
        text = "cuda:0" if available else "cpu"
    if text == "cpu":
        return Placement("cpu", deterministic=deterministic)
    if not available:
        built = torch.version.cuda or "none (a CPU-only torch build)"
        raise BenchError(f"--device {name}: torch {torch.__version__} sees no CUDA GPU on this machine (CUDA "
                         f"build: {built}); use --device cpu or auto")
    index = int(text.split(":")[1]) if ":" in text else 0
    count = torch.cuda.device_count()
    if index >= count:
        raise BenchError(f"--device {name}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return Placement(f"cuda:{index}", gpu=torch.cuda.get_device_name(index), cuda=torch.version.cuda,
                     cudnn=torch.backends.cudnn.version(), deterministic=deterministic)


@contextlib.contextmanager
def full_float32() -> Iterator[None]:
    """Within: no TF32 in cuDNN convolutions or CUDA matrix products (comparisons with the CPU); torch's
    `fp32_precision` settings, restored after."""
    import torch

    conv, matmul = torch.backends.cudnn.conv, torch.backends.cuda.matmul
    saved = conv.fp32_precision, matmul.fp32_precision
    conv.fp32_precision = matmul.fp32_precision = "ieee"
    try:
        yield
    finally:
        conv.fp32_precision, matmul.fp32_precision = saved


@contextlib.contextmanager
def determinism(placement: Placement) -> Iterator[None]:
    """Within, with `deterministic`: torch's deterministic algorithms (cuDNN's included) and full float32
    (TF32, on by default for cuDNN convolutions, rounds to 10 mantissa bits); every setting as it was after,
    so a run in a longer process (a sweep's worker, a test) leaves nothing behind. Bitwise equality across
    GPU models or library versions is still not promised (see README, determinism)."""
    if not placement.deterministic:
        yield
        return
    import torch

    saved = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
             torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic)
    workspace = os.environ.get("CUBLAS_WORKSPACE_CONFIG")
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # cuBLAS needs it for deterministic GEMMs
    torch.use_deterministic_algorithms(True)
    torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = False, True
    try:
        with full_float32():
            yield
    finally:
        torch.use_deterministic_algorithms(saved[0], warn_only=saved[1])
        torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = saved[2], saved[3]
        if workspace is None:
            os.environ.pop("CUBLAS_WORKSPACE_CONFIG", None)


@runtime_checkable
class DevicePlaced(Protocol):
    """Optional capability of an encoder or a task: compute on `device` from now on. An encoder without it
    runs on the CPU (the run says so in its notes); a task without it does all its work on the CPU."""

    def to_device(self, device: torch.device) -> None: ...


def cuda_rng_state() -> list[torch.Tensor]:
    """The CUDA generators' states for a checkpoint (empty when this process never used CUDA: asking
    would start a CUDA context in a CPU run)."""
    import torch

    return torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else []


def restore_cuda_rng_state(states: list[torch.Tensor] | None) -> None:
    """Inverse of `cuda_rng_state`; a checkpoint from a machine with more (or no) GPUs restores what fits.
    (A checkpoint loaded with `map_location` onto a GPU holds the states as CUDA tensors; the setter takes
    CPU ByteTensors.)"""
    import torch

    if states and torch.cuda.is_available():
        for index, state in enumerate(states[: torch.cuda.device_count()]):
            torch.cuda.set_rng_state(state.cpu(), index)
