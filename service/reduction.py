"""Reduction on entry: clouds above ``ENTRY_LIMIT`` points are cut to that many before anything else.

Full-resolution scans (fused RGB-D fragments, LiDAR sweeps, range images) hold 10^5-10^6 points, while the
network works on 768 and the refinement on a few thousand. Every later stage (isolated-point filter,
voxel grid, farthest-point sampling, refinement clouds) costs time and memory in proportion to the input, so
the pipeline first keeps a pseudo-random subset chosen by a hash of each point's coordinates: O(N) where no two
points coincide, independent of the order the points arrive in, and uniform over the surface (it keeps the scan's
density pattern, which the later stages handle). A stack of identical points counts once, so that it can neither
crowd the surface out nor, dropped whole, take every point with it. The hash is taken in blocks of
``ENTRY_BLOCK`` rows, so that the temporaries stay small beside the cloud itself.
"""

from __future__ import annotations

import numpy as np

from service.checks import MIN_POINTS
from service.sampling import coordinate_hash, lowest_distinct

ENTRY_LIMIT = 100_000  # points per cloud kept on entry
ENTRY_BLOCK = 65_536  # rows hashed at a time


def entry_indices(points: np.ndarray, limit: int = ENTRY_LIMIT, origin: np.ndarray | None = None
                  ) -> np.ndarray | None:
    """``None`` when ``points [N, 3]`` has at most ``limit`` rows, else the sorted int64 indices of ``limit`` rows
    with distinct coordinates: those whose coordinate hash (of the row minus ``origin [3]``, where given) is lowest
    (:func:`service.sampling.lowest_distinct`). Where the cloud holds fewer distinct points than that, each of them
    once; and where fewer than ``MIN_POINTS``, as many rows more of their stacks (the first rows not kept), so that
    the later stages still get a cloud of ``MIN_POINTS`` rows to judge.

    The lowest hashes are looked for among the rows whose hash falls in the lowest ``2 * limit / N`` of the range
    (about twice the limit), and among all rows only where those hold fewer than ``limit`` distinct points (stacks of
    identical points): the hashes of the whole cloud are not kept at once unless needed."""
    count = len(points)
    if count <= limit:
        return None
    rows, hashes = hashed_rows(points, origin, share=2 * limit / count)  # [C], [C]
    kept = lowest_distinct(hashes, limit, in_hash_order=False)  # [min(D, limit)] into rows
    if len(kept) < limit and len(rows) < count:  # too few distinct points below the share: look at every row
        rows, hashes = hashed_rows(points, origin, share=1.0)
        kept = lowest_distinct(hashes, limit, in_hash_order=False)
    kept = rows[kept]
    if len(kept) < MIN_POINTS:  # fewer distinct points than a cloud may hold: rows of their stacks as well
        more = np.setdiff1d(np.arange(min(count, MIN_POINTS + len(kept))), kept)[:MIN_POINTS - len(kept)]
        kept = np.concatenate([kept, more])
    return np.sort(kept).astype(np.int64)


def hashed_rows(points: np.ndarray, origin: np.ndarray | None, share: float) -> tuple[np.ndarray, np.ndarray]:
    """The rows ``[C]`` (ascending) of ``points [N, 3]`` whose coordinate hash (of the row minus ``origin``) lies in
    the lowest ``share`` of the hash range (every row for ``share >= 1``), and those hashes ``[C]``, taken in blocks
    of ``ENTRY_BLOCK`` rows."""
    every = share >= 1.0
    threshold = np.uint64(0 if every else int(share * 2**64))
    rows, hashes = [], []
    for start in range(0, len(points), ENTRY_BLOCK):
        block = points[start:start + ENTRY_BLOCK]  # [B, 3]
        if origin is not None:
            block = block - origin
        h = coordinate_hash(block)  # [B]
        below = np.arange(len(h)) if every else np.flatnonzero(h < threshold)
        rows.append(below + start)
        hashes.append(h[below])
    return np.concatenate(rows), np.concatenate(hashes)
