"""The C allocator setting every harness process starts with: freed large blocks stay in the heap.

glibc's malloc hands blocks above its mmap threshold (at most 32 MiB) to the kernel on every free, so a
training step's activations (pixels-cnn's first layer: 512 x 32 x 32 x 32 floats, 64 MiB) are mapped,
page-faulted and zeroed anew at every minibatch. Raising the threshold keeps them for reuse: a pixels-cnn
PPO minibatch on one core went from 1.51 s to 1.04 s (docs/PERFORMANCE.md). It changes no number, only
where memory comes from; elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
_KEEP_BYTES = 1 << 30   # blocks up to 1 GiB come from the heap, and the heap is not trimmed below that


@functools.cache
def keep_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds for this process; whether they were set (False off glibc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others have no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _KEEP_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, _KEEP_BYTES))
