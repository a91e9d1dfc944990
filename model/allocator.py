"""Keep freed memory in the process for CPU torch work (glibc ``mallopt``), instead of handing it back.

A training step, and an eager forward pass, allocate and free the same large buffers (2-40 MB: pair
tensors, edge tensors, their gradients) again and again. glibc's defaults give buffers above a dynamic
threshold their own ``mmap`` and trim the heap's free top back to the kernel, so every step pays page
faults and the kernel's zeroing of fresh pages on first touch: about a fifth of a fused CPU training step
and more than half of an eager evaluation batch on the development VM (``docs/BENCHMARKS.md``, "Keeping
freed memory"). With the thresholds raised, freed buffers are reused. Training and ``mfgnet evaluate
--checkpoint`` call it. The runtime does not: ONNX Runtime keeps its own arena, and the pipeline on
20,000-100,000-point inputs was slower with it (fresh ``mmap`` pages are zero already; heap blocks are not).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 * 1024 * 1024  # glibc's upper limit on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX)
TRIM_THRESHOLD = 2**31 - 1  # (mallopt takes an int) in effect never trim the heap's top
TOP_PAD = 512 * 1024 * 1024  # grow the heap in large steps


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process; returns whether they were set.

    A no-op (``False``) where the C library is not glibc (macOS, musl, Windows). Memory freed by the
    process is then reused by later allocations rather than returned to the kernel: the resident size
    stays near the peak of a step, which training reaches anyway.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    settings = ((M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX), (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_TOP_PAD, TOP_PAD))
    return all(mallopt(param, value) == 1 for param, value in settings)
