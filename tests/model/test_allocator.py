"""model.allocator: freed training buffers are reused instead of being faulted in again every step."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

FAULTS_SCRIPT = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from model.allocator import keep_freed_memory
    assert keep_freed_memory()
def step():  # as a training step: several large buffers alive at once, every page touched, all freed
    buffers = [np.ones(4 << 20, dtype=np.float32) for _ in range(4)]  # 4 x 16 MB
    del buffers
step()  # the first step grows the heap: not counted
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    step()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def minor_faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", FAULTS_SCRIPT, mode], capture_output=True, text=True, check=True)
    return int(out.stdout.split()[-1])


def huge_pages_always() -> bool:
    try:
        return "[always]" in Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mallopt thresholds are glibc's (Linux)")
@pytest.mark.skipif(huge_pages_always(), reason="transparent huge pages: too few faults to count either way")
def test_freed_buffers_are_reused_without_page_faults():
    default, kept = minor_faults("default"), minor_faults("keep")
    # default glibc hands freed buffers back to the kernel (mmap / trim): ~2,500 faults per step here
    assert default > 10 * 500
    assert kept < default / 10
