"""Free space of a range image: where its sensor saw through, a right pose puts no surface of the other scan.

A range image samples its surface on the sensor's pixel grid, so its density on the surface falls with the cosine of
the incidence angle. :func:`range_view` finds the viewing direction that best explains a cloud's density that way
(the correlation of log density and log ``|cos|`` over its points); a cloud it explains well (a correlation of at
least ``RANGE_IMAGE_CORRELATION``: single range images, not fused room fragments, LiDAR frames or uniform samples of
a mesh) gets a depth map along that direction: per cell of a grid across it, the nearest and the farthest depth seen.
Density and normals are read over ``VIEW_NEIGHBOURS`` neighbours; over ``COARSE_VIEW_NEIGHBOURS`` a range image
still explains its density through range noise of a point spacing (a coarser reading, twice the time). The grid's
cell follows the larger of the points' nearest-neighbour and mean spacings, so that a random share of a pixel grid,
near pairs among wide gaps, still fills its cells.

:func:`view_shares` then counts the points of the other scan, moved by a pose, that lie well in front of what the
sensor saw in a cell it saw: space the sensor looked through. Which end of the axis the sensor was on is not known
from the points, so both are tried and the smaller share counts; surface hidden from the sensor (behind what it saw,
or in cells it did not see) is no evidence either way. On the real range images measured, a right pose leaves a few
percent there and wrong poses 0.038 or more; a pose half a turn off, or one that overlays a low-overlap pair better
than the truth, that the other checks call ``reliable`` puts a tenth or more of the other scan in that space
(``docs/decisions/0053-free-space-of-range-images.md``, ``0054-free-space-settles-the-second-search.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.icp import smallest_eigenvectors
from service.kdtree import KDTree

RANGE_IMAGE_CORRELATION = 0.6  # range images 0.74-0.84; fused fragments and LiDAR frames 0.51 or less (over
# COARSE_VIEW_NEIGHBOURS 0.50 or less, but for a fragment cut by a plane at 0.62), mesh samples less
VIEW_QUERIES = 1000  # the points whose density and normal fit the direction (all points are their neighbours: a
# random share of a pixel grid would blur its density with sampling noise)
VIEW_NEIGHBOURS = 10
COARSE_VIEW_NEIGHBOURS = 40  # the coarser reading: noise of a point spacing turns 10 neighbours' normals to noise
# (docs/decisions/0094)
VIEW_DIRECTIONS = 300  # directions over a hemisphere tried first, then refined about the best
CELL_SPACINGS = 2.0  # the depth map's cell, in the view points' spacing (viewing_axis)
EDGE_CELLS = 2  # cells this close to an unseen one do not count as seen: a cut or cropped image's edge is no evidence
DEPTH_TOLERANCE_SPACINGS = 4.0  # how far in front of the seen depth a point must lie to count (noise, grazing cells)
MIN_COSINE = 0.05  # |cos| floor in the fit (grazing normals)
GRID_QUANTILE = 0.001  # the depth map spans the points between these quantiles across the axis: far strays lie off it
MAX_GRID_CELLS = 4_000_000  # above this the image is spread too thinly to map (two float64 maps: 64 MB)
_SEED = 0  # the queries are drawn the same way for the same cloud


@dataclass(frozen=True)
class RangeView:
    """A range image's viewing axis and depth map (cells ``[Gu * Gv]``, flattened)."""

    axis: np.ndarray  # [3] unit, the viewing direction up to its sign
    across: np.ndarray  # [2, 3] unit, spanning the image plane
    correlation: float  # of log density and log |cos| along ``axis``
    cell: float  # grid cell, in the cloud's units
    tolerance: float  # depth tolerance, the same units
    corner: np.ndarray  # [2] int64, the grid's lowest cell
    shape: tuple[int, int]
    nearest: np.ndarray  # [Gu * Gv] largest depth along +axis per cell (-inf: unseen)
    farthest: np.ndarray  # [Gu * Gv] smallest depth along +axis per cell (+inf: unseen)
    neighbours: int = VIEW_NEIGHBOURS  # the reading it came from (COARSE_VIEW_NEIGHBOURS: the coarser one)

    def cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The flat cell of each of ``points [N, 3]`` and whether it lies on the grid (``[N]`` each)."""
        return grid_cells(points @ self.across.T / self.cell, self.corner, self.shape)


def grid_cells(placed: np.ndarray, corner: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The flat cell (row-major, from ``corner [2]``) of each of ``placed [N, 2]`` (coordinates in cells) and whether
    it lies on a grid of ``shape`` (``[N]`` each); cells off it are 0, however far (no integer overflow)."""
    u = np.floor(placed[:, 0]) - corner[0]  # [N] float: compared before any cast
    v = np.floor(placed[:, 1]) - corner[1]
    on = (u >= 0) & (v >= 0) & (u < shape[0]) & (v < shape[1])
    return (np.where(on, u, 0) * shape[1] + np.where(on, v, 0)).astype(np.int64), on


def hemisphere(count: int) -> np.ndarray:
    """``[~count / 2, 3]`` unit directions spread evenly over the hemisphere ``z >= 0`` (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = np.pi * (1.0 + 5.0**0.5) * i
    dirs = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)
    return dirs[dirs[:, 2] >= 0]


def across_axis(axis: np.ndarray) -> np.ndarray:
    """``[2, 3]``: two unit vectors orthogonal to ``axis [3]`` and to each other."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(axis, u)])


def _correlations(log_density: np.ndarray, normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """``[D]`` correlation of ``log_density [Q]`` (centred) with log ``|cos|`` of ``normals [Q, 3]`` and ``dirs``."""
    log_cos = np.log(np.maximum(np.abs(normals @ dirs.T.astype(np.float32)), MIN_COSINE))  # [Q, D] float32
    log_cos -= log_cos.mean(axis=0)
    norms = np.linalg.norm(log_cos, axis=0) * np.linalg.norm(log_density)
    return (log_density @ log_cos) / np.maximum(norms, 1e-12)


def viewing_axis(points: np.ndarray, rng: np.random.Generator, tree: KDTree | None = None,
                 neighbours: int = VIEW_NEIGHBOURS) -> tuple[np.ndarray, float, float]:
    """The direction that best explains the density of ``points [N >= neighbours, 3]`` as a range image's, read over
    ``neighbours`` neighbours, its correlation, and the points' spacing: the larger of the median nearest-neighbour
    distance and the mean spacing the ``neighbours``-th neighbour's distance gives (a random share of a pixel grid
    leaves near pairs among wide gaps), 0 where that median is 0; ``tree``: a KD-tree of ``points`` already built."""
    tree = KDTree(points) if tree is None else tree
    queries = points[rng.choice(len(points), min(VIEW_QUERIES, len(points)), replace=False)]  # [Q, 3]
    dist, nb = tree.query(queries, k=neighbours)  # [Q, k]
    around = points[nb]  # [Q, k, 3]
    local = around - around.mean(axis=1, keepdims=True)
    normals = smallest_eigenvectors(np.einsum("qki,qkj->qij", local, local))[1].astype(np.float32)  # [Q, 3]
    log_density = -2.0 * np.log(np.maximum(dist[:, -1], 1e-12))  # k points within the k-th distance, on a surface
    log_density = (log_density - log_density.mean()).astype(np.float32)
    dirs = hemisphere(VIEW_DIRECTIONS)
    scores = _correlations(log_density, normals, dirs)
    best, score = dirs[int(np.argmax(scores))], float(scores.max())
    offsets = np.vstack([hemisphere(60), -hemisphere(60)])  # [~60, 3] nudges in every direction
    for step in (0.05, 0.02):
        near = best + step * offsets
        near /= np.linalg.norm(near, axis=1, keepdims=True)
        near_scores = _correlations(log_density, normals, near)
        if near_scores.max() > score:
            best, score = near[int(np.argmax(near_scores))], float(near_scores.max())
    nearest = float(np.median(dist[:, 1]))  # 0 where most points are stacked duplicates: no view (range_view)
    mean_spacing = float(np.median(dist[:, -1])) * np.sqrt(np.pi / (neighbours - 1))  # k points on the k-th's disc
    return best, score, max(nearest, mean_spacing) if nearest > 0 else 0.0


def range_view(points: np.ndarray, tree: KDTree | None = None, neighbours: int = VIEW_NEIGHBOURS
               ) -> RangeView | None:
    """The :class:`RangeView` of ``points [N, 3]`` (all of them: the entry reduction bounds ``N``), read over
    ``neighbours`` neighbours, or ``None`` where their density does not follow a viewing direction (correlation below
    ``RANGE_IMAGE_CORRELATION``) or they are too few to tell; ``tree``: a KD-tree of ``points`` where one is built
    already."""
    if len(points) < 4 * neighbours:
        return None
    cloud = np.asarray(points, dtype=np.float64)  # [N, 3]
    axis, correlation, spacing = viewing_axis(cloud, np.random.default_rng(_SEED), tree, neighbours)
    if correlation < RANGE_IMAGE_CORRELATION or not spacing > 0:
        return None
    across, cell = across_axis(axis), CELL_SPACINGS * spacing
    placed = cloud @ across.T / cell  # [N, 2] in cells
    low, high = np.quantile(placed, [GRID_QUANTILE, 1.0 - GRID_QUANTILE], axis=0)  # [2] each: strays off the grid
    if np.prod(high - low + 1.0) > MAX_GRID_CELLS:
        return None  # a sparse image spread too wide to map within bounded memory
    corner = np.floor(low).astype(np.int64)
    shape = (int(np.floor(high[0])) - int(corner[0]) + 1, int(np.floor(high[1])) - int(corner[1]) + 1)
    flat, on = grid_cells(placed, corner, shape)
    flat = flat[on]
    depth = cloud[on] @ axis
    nearest = np.full(shape[0] * shape[1], -np.inf)
    farthest = np.full(shape[0] * shape[1], np.inf)
    np.maximum.at(nearest, flat, depth)
    np.minimum.at(farthest, flat, depth)
    inner = away_from_edges(np.isfinite(nearest).reshape(shape), EDGE_CELLS).ravel()  # [Gu * Gv]
    nearest[~inner], farthest[~inner] = -np.inf, np.inf
    return RangeView(axis, across, correlation, cell, DEPTH_TOLERANCE_SPACINGS * spacing, corner, shape, nearest,
                     farthest, neighbours)


def away_from_edges(seen: np.ndarray, cells: int) -> np.ndarray:
    """``seen [Gu, Gv]`` eroded by ``cells``: a cell stays where every cell within ``cells`` steps along the grid's
    axes and diagonals is seen."""
    inner = seen.copy()
    for _ in range(cells):
        padded = np.pad(inner, 1, constant_values=False)
        inner = np.logical_and.reduce([padded[1 + du:padded.shape[0] - 1 + du, 1 + dv:padded.shape[1] - 1 + dv]
                                       for du in (-1, 0, 1) for dv in (-1, 0, 1)])
    return inner


def view_shares(view: RangeView, points: np.ndarray) -> tuple[float, float]:
    """The share of ``points [N, 3]`` (in the view's frame) that lie in front of what ``view`` saw in a seen cell, by
    more than its tolerance, with the sensor at whichever end of the axis gives the smaller share; and the share that
    lies in a seen cell at all (the evidence the first rests on)."""
    if len(points) == 0:
        return 0.0, 0.0
    flat, on = view.cells(points)
    depth = points @ view.axis  # [N]
    seen = on & np.isfinite(view.nearest[flat])
    plus = np.count_nonzero(seen & (depth > view.nearest[flat] + view.tolerance))
    minus = np.count_nonzero(seen & (depth < view.farthest[flat] - view.tolerance))
    return min(plus, minus) / len(points), np.count_nonzero(seen) / len(points)


@dataclass(frozen=True)
class PoseFreeSpace:
    """What a pose puts in the range images' views, the larger of the two ways (:func:`pose_free_space`)."""

    share: float  # of one scan's points, where the other scan's sensor saw through
    seen: float  # of one scan's points, in cells the other scan's sensor saw


def pose_free_space(source_view: RangeView | None, target_view: RangeView | None, source: np.ndarray,
                    target: np.ndarray, R: np.ndarray, t: np.ndarray) -> PoseFreeSpace | None:
    """The larger :func:`view_shares` of the pose ``src_to_tgt = (R, t)`` both ways: ``source [N, 3]`` moved into
    ``target_view`` and ``target [M, 3]`` moved back into ``source_view``; ``None`` where neither cloud is a range
    image."""
    shares = []
    if target_view is not None:
        shares.append(view_shares(target_view, source @ R.T + t))
    if source_view is not None:
        shares.append(view_shares(source_view, (target - t) @ R))
    if not shares:
        return None
    return PoseFreeSpace(max(free for free, _ in shares), max(seen for _, seen in shares))
