"""Reduction on entry: clouds above ``ENTRY_LIMIT`` points are cut to about that many before anything else.

Full-resolution scans (fused RGB-D fragments, LiDAR sweeps, range images) hold 10^5-10^6 points, while the
network works on 768 and the refinement on a few thousand. Every later stage (isolated-point filter,
voxel grid, farthest-point sampling, refinement clouds) costs time and memory in proportion to the input, so
the pipeline first keeps a pseudo-random subset chosen by a hash of each point's coordinates: O(N), no sort,
independent of the order the points arrive in, and uniform over the surface (it keeps the scan's density
pattern, which the later stages handle). The hash is taken in blocks of ``ENTRY_BLOCK`` rows, so that the
temporaries stay small beside the cloud itself.
"""

from __future__ import annotations

import numpy as np

from service.sampling import coordinate_hash

ENTRY_LIMIT = 100_000  # points per cloud kept on entry
ENTRY_BLOCK = 65_536  # rows hashed at a time


def entry_indices(points: np.ndarray, limit: int = ENTRY_LIMIT, origin: np.ndarray | None = None
                  ) -> np.ndarray | None:
    """``None`` when ``points [N, 3]`` has at most ``limit`` rows, else the sorted int64 indices of about
    ``limit`` of them: each kept when the coordinate hash of its row minus ``origin [3]`` (where given) falls below
    ``limit / N`` of the hash range."""
    count = len(points)
    if count <= limit:
        return None
    threshold = np.uint64(min(2**64 - 1, int(limit / count * 2**64)))
    kept = []
    for start in range(0, count, ENTRY_BLOCK):
        block = points[start:start + ENTRY_BLOCK]  # [B, 3]
        if origin is not None:
            block = block - origin
        kept.append(np.flatnonzero(coordinate_hash(block) < threshold) + start)
    return np.concatenate(kept).astype(np.int64)
