"""The allocator setting: a freed large block is reused without being page-faulted again."""

import subprocess
import sys

import pytest

from mftcn_bench.core.allocator import keep_freed_memory

# Allocate, touch and free a 64 MiB block twice; print the minor page faults of the second time.
_PROGRAM = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from mftcn_bench.core.allocator import keep_freed_memory
    assert keep_freed_memory()
def touch():
    block = np.empty(64 << 20, dtype=np.uint8)
    block[::4096] = 1
    del block
touch()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
touch()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _second_touch_faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _PROGRAM, mode], capture_output=True, text=True, check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(not keep_freed_memory(), reason="needs glibc's mallopt")
def test_a_freed_large_block_is_reused_without_page_faults():
    huge_pages = (64 << 20) // (2 << 20)  # 32 faults at least, with transparent huge pages (16,384 without)
    assert _second_touch_faults("default") >= huge_pages  # glibc unmapped it: it is mapped and zeroed again
    assert _second_touch_faults("keep") < 4               # kept in the heap: already mapped
