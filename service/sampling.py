"""Deterministic, order-independent resampling of a point cloud to the network's working size.

The indices returned by :func:`resample_indices` depend only on the geometry of the cloud, never
on the order in which the points arrive: permuting the input selects the same points (same
coordinates, same output order).  Only points that share identical coordinates can come back under
different indices, and then the coordinates are the same.

Strategy:

* ``drop_isolated``: isolated points (:func:`isolated_points`: flying pixels, sparse clutter) are left out
  first (of all points, or of the voxel representatives below), so that farthest-point sampling, which
  favours points far from all others, does not spend the working size on them; unless fewer than ``MIN_POINTS``
  would be left (:func:`kept_unless_too_few`).
* A stack of identical points counts once (:func:`distinct_rows`), unless fewer than ``MIN_POINTS`` distinct points
  are left.
* ``N <= size``: every point, in canonical order (lexicographic by ``x, y, z``, ties by index).
* ``size < N <= VOXEL_TRIGGER * size``: farthest-point sampling (FPS) on all points.
* ``N > VOXEL_TRIGGER * size``: an order-independent voxel-grid reduction to roughly
  ``VOXEL_TARGET * size`` representatives first (each voxel keeps the point closest to the voxel's
  centre), then FPS on those.  200,000 points take a few tens of milliseconds.  With ``drop_isolated`` the
  voxels of scattered points are left out; where they were most of the grid's voxels, the grid was sized for
  them rather than for the surface, and is made again on the points of the others.

FPS starts from the point farthest from the centroid and always runs on candidates sorted in
canonical order, so every ``argmax`` tie is broken lexicographically by coordinates.
"""

from __future__ import annotations

import numpy as np

from service.checks import MIN_POINTS
from service.kdtree import KDTree

DEFAULT_SIZE = 768  # working size W of the network
# isolated_points: a point is isolated when its mean distance to its ISOLATED_NEIGHBOURS nearest others exceeds
# ISOLATED_FACTOR times the cloud's median of that distance. Chosen on the 170 dense / 300 sparse test pairs
# with and without 20% / 40% uniform outliers (docs/ACCURACY.md, "Outliers"): it drops no point of the clean
# dense pairs and 0.1% of the sparse ones; 2.5 (more outliers caught) or a MAD rule cost clean pairs.
ISOLATED_NEIGHBOURS = 8
ISOLATED_FACTOR = 3.0
ISOLATED_PASSES = 2  # a second pass on the rest: dense pairs with 40% outliers 0.706 -> 0.765 within 5 deg
VOXEL_TRIGGER = 8  # reduce with a voxel grid first when N > VOXEL_TRIGGER * size
VOXEL_TARGET = 3.5  # aim for about this many occupied voxels per requested point ...
VOXEL_ACCEPT = (3.0, 4.0)  # ... and accept a voxel size whose occupancy / size lies in this range
# Where fewer than REGRID_SHARE of the grid's voxels hold more than scattered points (sparse_voxels), the
# scattered points sized the grid (too coarse for the surface; the representatives of many surface voxels are
# scattered points): the grid is made again on the points of the other voxels. Clean real scans keep 0.59-1.0.
REGRID_SHARE = 0.5
# Where the sparse voxels' points stretch the bounding box over this many times the extent of the others, they sized
# the grid, and it is made again without them (_near_rows): a point 1e5 times a 0.2 m scan's size away left 122
# voxels, 1e6 times 2, and a `collinear` working cloud; 1e4 times still leaves thousands.
FAR_EXTENT_RATIO = 1000.0
# spread_indices: where the grid holds fewer than SPREAD_SHARE of the points asked for (once the sparse voxels and
# isolated points are dropped), it is made finer for the share missing, at most SPREAD_REGRIDS times (refine_points
# 2048 of a 64,000-point LiDAR frame kept 1,040 points on one grid)
SPREAD_SHARE = 0.85
SPREAD_REGRIDS = 2
VOXEL_MAX_TRIES = 6  # voxel-size adjustments (each counts the occupied voxels of N keys once)
VOXEL_MAX_CELLS_PER_AXIS = 1_000_000  # keeps linear voxel keys far from int64 overflow
# Voxel keys are counted with a table (np.bincount) while the grid has at most this many cells per point, plus
# COUNT_TABLE_MIN_CELLS; beyond that (a fine grid over scattered points) by sorting. A surface's grid holds a few
# tens of thousands of cells, and the table counts 44,000 keys ~14x faster than a sort.
COUNT_TABLE_CELLS_PER_POINT = 8
COUNT_TABLE_MIN_CELLS = 65_536


def resample_indices(points: np.ndarray, size: int = DEFAULT_SIZE, drop_isolated: bool = False,
                     regrid: bool = True) -> np.ndarray:
    """Indices of ``min(N, size)`` points chosen by geometry alone (fewer with ``drop_isolated``, or where points
    repeat a coordinate).

    Args:
        points: ``(N, 3)`` finite coordinates (any float dtype).
        size: number of points wanted (``>= 1``).
        drop_isolated: leave out :func:`isolated_points` first.
        regrid: where most voxels of the grid hold only scattered points (:data:`REGRID_SHARE`), make the grid
            again on the points of the others (once: the inner call passes ``False``).

    Returns:
        ``(min(C, size),)`` int64 indices into ``points`` of the ``C`` candidates (every distinct point, or one per
        voxel above ``VOXEL_TRIGGER * size``, less the isolated ones): all of them in canonical order when
        ``C <= size``, else the farthest-point-sampling picks in the order they were picked (so any
        prefix is itself a well-spread subsample).

    Raises:
        ValueError: ``points`` is not ``(N, 3)``, holds NaN/Inf, or ``size < 1``.
    """
    points = _checked(points, size)
    n = points.shape[0]
    if n > VOXEL_TRIGGER * size:
        candidates, occupancy, group = _voxel_grid(points, size)
        if candidates.shape[0] < size:  # too few distinct places: far points sized the grid, or heavy duplication
            near = _near_rows(points, candidates, sparse_voxels(occupancy), group) if drop_isolated and regrid else None
            if near is not None:
                return near[resample_indices(points[near], size, drop_isolated, regrid=False)]
            candidates = distinct_rows(points, np.arange(n))  # every distinct point
        elif drop_isolated:  # voxels of scattered points hold one or two points, surface voxels many
            sparse = sparse_voxels(occupancy)  # [V]
            candidates = kept_unless_too_few(candidates, sparse)
            if regrid and candidates.shape[0] < REGRID_SHARE * len(sparse):  # scattered points sized the grid
                kept = np.flatnonzero(~sparse[group])  # [N'] rows in voxels that are not sparse
                return kept[resample_indices(points[kept], size, drop_isolated, regrid=False)]
    else:
        candidates = distinct_rows(points, np.arange(n))
    if drop_isolated and candidates.shape[0] <= VOXEL_TRIGGER * size:  # bounded cost (else heavy duplication)
        candidates = kept_unless_too_few(candidates, isolated_points(points[candidates]))
    candidates = candidates[canonical_order(points[candidates])]  # ties -> lexicographic order
    if candidates.shape[0] <= size:
        return candidates.astype(np.int64)
    picks = _farthest_point_sampling(points[candidates], size)  # [size] into candidates
    return candidates[picks].astype(np.int64)


def spread_indices(points: np.ndarray, size: int, drop_isolated: bool = False, regrid: bool = True) -> np.ndarray:
    """Indices of at most ``size`` well-spread points, in canonical order: a cheaper, less even sample than
    :func:`resample_indices` for large ``size`` (the refinement's clouds, ``refine_points``).

    Every point when ``N <= size``; else one point per occupied voxel of a grid sized for about ``size`` of
    them (:func:`_voxel_grid`; made finer, at most ``SPREAD_REGRIDS`` times, where it holds fewer than
    ``SPREAD_SHARE`` of ``size`` once ``drop_isolated`` dropped sparse voxels and isolated points), and where that gives
    more than ``size``, those whose coordinates hash lowest (:func:`coordinate_hash`) -- no farthest-point sampling,
    whose cost grows with ``size`` times the candidates (8192 of 200,000 points: 0.8 s). Order-independent like
    :func:`resample_indices`; ``drop_isolated`` and ``regrid`` (here: only where far points sized the grid) as there.
    """
    points = _checked(points, size)
    n = points.shape[0]
    if n <= size:
        return resample_indices(points, size, drop_isolated)
    voxels = size  # the grid's aim: about this many occupied voxels
    for _ in range(SPREAD_REGRIDS + 1):
        candidates, occupancy, group = _voxel_grid(points, max(1, int(np.ceil(voxels / VOXEL_TARGET))))
        if drop_isolated:
            sparse = sparse_voxels(occupancy)  # [V]
            near = _near_rows(points, candidates, sparse, group) if regrid else None
            if near is not None:
                return near[spread_indices(points[near], size, drop_isolated, regrid=False)]
            candidates = kept_unless_too_few(candidates, sparse)
            candidates = kept_unless_too_few(candidates, isolated_points(points[candidates]))
        if candidates.shape[0] >= SPREAD_SHARE * size or voxels >= n:
            break
        # the drops took a share of the grid (a LiDAR frame's far range: half of it), or far points sized it
        voxels = min(n, int(np.ceil(voxels * size / max(candidates.shape[0], 1))))
    if candidates.shape[0] > size:
        candidates = candidates[np.argsort(coordinate_hash(points[candidates]), kind="stable")[:size]]
    return candidates[canonical_order(points[candidates])].astype(np.int64)


def _near_rows(points: np.ndarray, representatives: np.ndarray, sparse: np.ndarray, group: np.ndarray
               ) -> np.ndarray | None:
    """The rows of ``points [N, 3]`` outside the grid's ``sparse [V]`` voxels where those stretch the bounding box over
    ``FAR_EXTENT_RATIO`` times the rest's extent (measured on the voxels' ``representatives [V]``), else ``None``.
    A few points that far sized the grid (at most ``VOXEL_MAX_CELLS_PER_AXIS`` cells per axis) so coarse that the
    whole surface fell in a few voxels, and its sample was the far points and a handful of surface points."""
    dense = representatives[~sparse]  # [V'] rows
    if not sparse.any() or len(dense) == 0:
        return None
    extent = float(np.ptp(points[representatives], axis=0).max())
    if extent <= FAR_EXTENT_RATIO * float(np.ptp(points[dense], axis=0).max()):
        return None
    near = np.flatnonzero(~sparse[group])  # [N'] rows in voxels that are not sparse
    return near if len(near) >= MIN_POINTS else None


def _checked(points: np.ndarray, size: int) -> np.ndarray:
    """``points`` as a float64 ``(N, 3)`` array, or ``ValueError`` (wrong shape, NaN/Inf, ``size < 1``)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    points = points.astype(np.float64, copy=False)
    if not np.isfinite(points).all():
        raise ValueError("points contain NaN or Inf")
    return points


def coordinate_hash(points: np.ndarray) -> np.ndarray:
    """``(N,)`` uint64 hash of each row's float64 bit pattern (splitmix64 steps): a pseudo-random order that
    depends only on the coordinates, the same on every machine."""
    bits = np.ascontiguousarray(points, dtype=np.float64).view(np.uint64)  # [N, 3]
    h = np.zeros(points.shape[0], dtype=np.uint64)
    with np.errstate(over="ignore"):
        for column in range(3):
            h = (h ^ bits[:, column]) + np.uint64(0x9E3779B97F4A7C15)
            h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(31))
    return h


def hashed_indices(points: np.ndarray, size: int) -> np.ndarray:
    """Indices of up to ``size`` rows of ``points (N, 3)`` with distinct coordinates: those whose coordinates hash
    lowest (:func:`coordinate_hash`), in hash order (every distinct point when there are no more than ``size``). A
    pseudo-random uniform subsample that keeps each region's share of the points, chosen by the coordinates alone (so
    independent of their order) and 2-9x cheaper than :func:`spread_indices` on the real-scan set's
    22,000-43,000-point targets (4,096 points). A stack of identical points (a sensor's invalid ``(0, 0, 0)``
    returns) counts once."""
    points = _checked(points, size)
    return lowest_distinct(coordinate_hash(points), size)


def lowest_distinct(hashes: np.ndarray, size: int, in_hash_order: bool = True) -> np.ndarray:
    """``[min(D, size)]`` int64 rows of the ``size`` lowest of the ``D`` distinct values of ``hashes [N]`` (uint64),
    one row each (the first, where a value repeats), in hash order (``in_hash_order=False``: in any order, which
    spares a sort where no value repeats)."""
    if hashes.shape[0] > size:
        lowest = np.argpartition(hashes, size - 1)[:size]  # [size] in no particular order
        if in_hash_order:
            lowest = lowest[np.argsort(hashes[lowest], kind="stable")]  # [size] rows in hash order
            picked = hashes[lowest]
        else:
            picked = np.sort(hashes[lowest])  # [size] their hashes, sorted
        if np.all(picked[1:] != picked[:-1]):  # no two picks share their coordinates
            return lowest.astype(np.int64)
    first = np.unique(hashes, return_index=True)[1]  # [D] each distinct value's first row, in hash order
    return first[:size].astype(np.int64)


def distinct_rows(points: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``rows [C]`` of ``points (N, 3)`` less the repeats of a coordinate (each coordinate's first row is kept, in
    ``rows``' order), unless fewer than ``MIN_POINTS`` would be left (:func:`kept_unless_too_few`): a stack of
    identical points is one point of the surface, and counted as many would pass for overlap."""
    first = np.unique(coordinate_hash(points[rows]), return_index=True)[1]  # [D] positions in rows
    if first.shape[0] == rows.shape[0]:
        return rows
    repeat = np.ones(rows.shape[0], dtype=bool)
    repeat[first] = False
    return kept_unless_too_few(rows, repeat)


def distinct_count(points: np.ndarray) -> int:
    """How many distinct coordinates ``points (N, 3)`` hold (rows of equal float64 bit patterns count once)."""
    return int(np.unique(coordinate_hash(points)).shape[0])


def kept_unless_too_few(candidates: np.ndarray, drop: np.ndarray) -> np.ndarray:
    """``candidates [C]`` less those ``drop [C]`` marks, unless fewer than ``MIN_POINTS`` (or than ``C``) would be left:
    a filter never leaves the network fewer points than a request may send (its neighbour graph needs a dozen)."""
    kept = candidates[~drop]
    return kept if kept.shape[0] >= min(MIN_POINTS, candidates.shape[0]) else candidates


def isolated_points(points: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: points of ``points (N, 3)`` whose mean distance to their ``ISOLATED_NEIGHBOURS`` nearest
    others is above ``ISOLATED_FACTOR`` times the median of that over the cloud, in ``ISOLATED_PASSES``
    passes (each on the points the previous ones kept: in a heavily contaminated cloud the scattered points
    inflate the first median). Fewer than half per pass, by the median; none when all points coincide or
    there are too few to have that many neighbours; zero spacings (stacked duplicates) stay out of the median.
    """
    isolated = np.zeros(points.shape[0], dtype=bool)
    for _ in range(ISOLATED_PASSES):
        remaining = np.flatnonzero(~isolated)
        found = _isolated_once(points[remaining])
        if not found.any():
            break
        isolated[remaining[found]] = True
    return isolated


def _isolated_once(points: np.ndarray) -> np.ndarray:
    """One pass of :func:`isolated_points`."""
    n = points.shape[0]
    if n <= ISOLATED_NEIGHBOURS:
        return np.zeros(n, dtype=bool)
    spacing = KDTree(points).query(points, k=ISOLATED_NEIGHBOURS + 1)[0][:, 1:].mean(axis=1)  # [N]
    spread = spacing[spacing > 0]  # stacked duplicates (e.g. a sensor's invalid (0, 0, 0) returns) do not count
    return spacing > ISOLATED_FACTOR * np.median(spread) if spread.size else np.zeros(n, dtype=bool)


def sparse_voxels(occupancy: np.ndarray) -> np.ndarray:
    """``(V,)`` bool: voxels holding fewer than ``1 / ISOLATED_FACTOR**2`` of the points that the voxel of a
    typical point holds (a median over points, not over voxels: scattered points can occupy most voxels;
    each voxel weighs at most as much as the 90th percentile of the counts, so one stack of duplicates
    cannot be the typical voxel). On a surface a voxel's count grows with the inverse square of the point
    spacing, so this matches :func:`isolated_points`' spacing rule."""
    counts = np.sort(occupancy)
    weights = np.minimum(counts, np.percentile(counts, 90))  # [V]
    typical = counts[np.searchsorted(np.cumsum(weights), weights.sum() / 2)]  # the voxel count of a typical point
    return occupancy < typical / ISOLATED_FACTOR**2


def canonical_order(points: np.ndarray) -> np.ndarray:
    """``(N,)`` int64 permutation sorting ``points (N, 3)`` by ``x``, then ``y``, ``z``, then index."""
    index = np.arange(points.shape[0])
    return np.lexsort((index, points[:, 2], points[:, 1], points[:, 0])).astype(np.int64)


def evenly_spaced_indices(count: int, size: int) -> np.ndarray:
    """Ascending indices of ``min(count, size)`` rows spread evenly through ``count`` rows (every row when
    ``count <= size``). On a working cloud, whose row order depends on geometry alone, the subset does too;
    unlike farthest-point sampling it keeps each region's share of the points, so stray points are not
    favoured (with 40% scattered outliers FPS subsets cost the rotation search 8 of 170 dense pairs)."""
    if count <= size:
        return np.arange(count, dtype=np.int64)
    return np.unique(np.linspace(0, count - 1, size).round().astype(np.int64))


def _farthest_point_sampling(points: np.ndarray, size: int) -> np.ndarray:
    """FPS picks ``(size,)`` into ``points (M, 3)`` (``M >= size``), starting farthest from the centroid.

    ``np.argmax`` returns the first maximum, so ties go to the earliest point in the given order.
    Picked points get a distance of -1 and are never picked twice, even among duplicates.
    """
    x, y, z = (np.ascontiguousarray(points[:, k]) for k in range(3))  # [M] each
    centroid = points.mean(axis=0)  # [3]
    min_dist2 = (x - centroid[0]) ** 2 + (y - centroid[1]) ** 2 + (z - centroid[2]) ** 2  # [M]
    i = int(np.argmax(min_dist2))  # start: farthest from the centroid
    min_dist2[:] = np.inf
    picks = np.empty(size, dtype=np.int64)
    dist2 = np.empty_like(x)
    scratch = np.empty_like(x)
    for k in range(size):
        picks[k] = i
        np.subtract(x, x[i], out=dist2)
        np.multiply(dist2, dist2, out=dist2)
        np.subtract(y, y[i], out=scratch)
        np.multiply(scratch, scratch, out=scratch)
        np.add(dist2, scratch, out=dist2)
        np.subtract(z, z[i], out=scratch)
        np.multiply(scratch, scratch, out=scratch)
        np.add(dist2, scratch, out=dist2)
        np.minimum(min_dist2, dist2, out=min_dist2)
        min_dist2[i] = -1.0
        i = int(np.argmax(min_dist2))
    return picks


def _voxel_grid(points: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices ``[V]`` of one point per occupied voxel, ~``VOXEL_TARGET * size`` of them, in any order, the number
    of points in each one's voxel ``[V]``, and for every point the position of its voxel's representative ``[N]``.

    The grid is anchored at the bounding-box minimum and its voxel size depends only on the bounding
    box and on occupancy counts, so the result does not depend on the input order.  Each voxel is
    represented by the original point closest to the voxel's centre (ties: lexicographic).
    """
    coords = np.ascontiguousarray(points.T)  # [3, N]: column reductions are much faster this way
    lo = coords.min(axis=1)  # [3]
    extent = coords.max(axis=1) - lo  # [3]
    if not extent.max() > 0:  # every point identical
        picks = canonical_order(points)[:size]
        return picks, np.full(len(picks), len(points)), np.zeros(len(points), dtype=np.int64)
    offsets = coords - lo[:, None]  # [3, N], >= 0
    target = VOXEL_TARGET * size
    min_voxel = extent.max() / VOXEL_MAX_CELLS_PER_AXIS
    # First guess: the points lie on a surface of about half the bounding box's surface area.
    area = extent[0] * extent[1] + extent[1] * extent[2] + extent[2] * extent[0]
    voxel = float(np.sqrt(area / target)) if area > 0 else float(extent.max() / target)
    tried: list[tuple[float, int]] = []
    for _ in range(VOXEL_MAX_TRIES):
        voxel = max(voxel, min_voxel)
        count = _occupied_voxels(*_voxel_keys(np.floor(offsets / voxel), extent, voxel))
        tried.append((voxel, count))
        if VOXEL_ACCEPT[0] * size <= count <= VOXEL_ACCEPT[1] * size:
            break
        # occupancy ~ voxel^-d: d = 2 for a surface at first, then estimated from the last two tries
        d = 2.0
        if len(tried) >= 2:
            (v0, c0), (v1, c1) = tried[-2], tried[-1]
            if v0 != v1 and c0 > 0 and c1 > 0 and c0 != c1:
                d = float(np.clip(-np.log(c1 / c0) / np.log(v1 / v0), 1.0, 3.0))
        voxel = voxel * (max(count, 1) / target) ** (1.0 / d)
    # Keep the try closest to the target (in ratio), preferring those with at least `size` voxels.
    voxel, _ = min(tried, key=lambda vc: (vc[1] < size, abs(np.log(max(vc[1], 1) / target))))

    cell = np.floor(offsets / voxel)  # [3, N] voxel coordinates of each point
    keys, cells = _voxel_keys(cell, extent, voxel)  # [N], and the grid's number of cells
    from_centre = offsets - (cell + 0.5) * voxel  # [3, N]
    dist2 = from_centre[0] ** 2 + from_centre[1] ** 2 + from_centre[2] ** 2  # [N] to the voxel centre
    group, occupancy = _voxel_numbers(keys, cells)  # [N] voxel number of each point (rank of its key), [V] counts
    group_min = np.full(len(occupancy), np.inf)
    np.minimum.at(group_min, group, dist2)  # [V] each voxel's smallest distance to its centre
    candidates = np.flatnonzero(dist2 == group_min[group])  # usually one per voxel
    candidate_group = group[candidates]
    c = points[candidates]  # [C, 3]
    tie_order = np.lexsort((candidates, c[:, 2], c[:, 1], c[:, 0], candidate_group))
    first = np.ones(tie_order.shape[0], dtype=bool)
    first[1:] = candidate_group[tie_order][1:] != candidate_group[tie_order][:-1]
    voxel_of = candidate_group[tie_order[first]]  # [V] the voxel number of each representative
    rank = np.empty(len(voxel_of), dtype=np.int64)
    rank[voxel_of] = np.arange(len(voxel_of))  # voxel number -> representative
    return candidates[tie_order[first]], occupancy[voxel_of], rank[group]


def _voxel_keys(cell: np.ndarray, extent: np.ndarray, voxel: float) -> tuple[np.ndarray, int]:
    """``(N,)`` int64 linear key of the voxel coordinates ``cell (3, N)`` (non-negative, floored), and the number of
    cells of the grid (every key is below it)."""
    cells = np.floor(extent / voxel).astype(np.int64) + 1  # [3] cells per axis
    ijk = cell.astype(np.int64)  # [3, N]
    return ijk[0] + cells[0] * (ijk[1] + cells[1] * ijk[2]), int(np.prod(cells))


def _count_table(cells: int, count: int) -> bool:
    """Whether keys below ``cells`` of ``count`` points are counted with a table of ``cells`` entries
    (``np.bincount``, O(N + cells)) rather than by sorting them (O(N log N)): grids of up to
    ``COUNT_TABLE_CELLS_PER_POINT`` cells per point, plus ``COUNT_TABLE_MIN_CELLS``."""
    return cells <= COUNT_TABLE_CELLS_PER_POINT * count + COUNT_TABLE_MIN_CELLS


def _voxel_numbers(keys: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``keys (N,)`` (below ``cells``) numbered by its rank among the distinct keys ``(N,)``, and the count of
    each distinct key ``(V,)``, in key order."""
    if _count_table(cells, len(keys)):
        counts = np.bincount(keys, minlength=cells)  # [cells]
        occupied = np.flatnonzero(counts)  # [V] the distinct keys, ascending
        rank = np.zeros(cells, dtype=np.int64)
        rank[occupied] = np.arange(len(occupied))
        return rank[keys], counts[occupied]
    _, group, occupancy = np.unique(keys, return_inverse=True, return_counts=True)
    return group.reshape(-1), occupancy


def _occupied_voxels(keys: np.ndarray, cells: int) -> int:
    """Number of distinct ``keys (N,)`` below ``cells`` (a count table or a plain sort: both faster than
    ``np.unique`` here)."""
    if _count_table(cells, len(keys)):
        return int(np.count_nonzero(np.bincount(keys, minlength=cells)))
    sorted_keys = np.sort(keys)
    return int(np.count_nonzero(sorted_keys[1:] != sorted_keys[:-1])) + 1
