"""The peak of the memory Python traces (numpy arrays and Python buffers) while a call runs."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable


def peak_bytes(read: Callable[[], object]) -> int:
    """Peak bytes traced while ``read()`` runs."""
    tracemalloc.start()
    try:
        read()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak
