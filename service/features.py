"""Rotation-invariant local shape descriptors for a coarse pose at any orientation.

Each point's descriptor is a histogram of the point pairs it forms with its neighbours within a radius, smoothed
over those neighbours (after FPFH: Rusu, Blodow and Beetz, ICRA 2009). Normals come from PCA, so their sign is
unknown; the pair features are those a normal flip leaves unchanged: ``|n_p . d|``, ``|n_q . d|``, ``|n_p . n_q|``
(``d`` the unit direction from ``p`` to ``q``) and ``|q - p| / radius``. None of them changes when the cloud turns
or moves, so matching descriptors pairs the same surface in two scans whatever their relative orientation.
"""

from __future__ import annotations

import numpy as np

from service.icp import smallest_eigenvectors
from service.kdtree import KDTree

BINS = 11  # histogram bins per pair feature
PAIR_FEATURES = 4
NORMAL_NEIGHBOURS = 16  # points in each normal's PCA
DESCRIBED_NEIGHBOURS = 32  # nearest neighbours a descriptor counts (those within the radius)


def voxel_means(points: np.ndarray, voxel: float) -> np.ndarray:
    """``[V, 3]`` the mean of the points ``[N, 3]`` in each occupied cell of a grid of ``voxel`` edges, in the order
    of the cells' keys (so independent of the points' order up to rounding)."""
    cell = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)  # [N, 3]
    dims = cell.max(axis=0) + 1  # [3]
    keys = cell[:, 0] + dims[0] * (cell[:, 1] + dims[1] * cell[:, 2])  # [N]
    _, group, counts = np.unique(keys, return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    sums = np.stack([np.bincount(group, points[:, k], len(counts)) for k in range(3)], axis=1)  # [V, 3]
    return sums / counts[:, None]


def describe(points: np.ndarray, radius: float) -> np.ndarray:
    """``[N, PAIR_FEATURES * BINS]`` float32 descriptors of ``points [N, 3]`` (``N > DESCRIBED_NEIGHBOURS``): each
    point's histogram of pair features over its neighbours within ``radius``, plus the mean of its neighbours'
    histograms weighted by inverse distance. Each histogram sums to 1 per feature (0 without a neighbour)."""
    n = len(points)
    k = min(DESCRIBED_NEIGHBOURS, n - 1)
    distance, neighbour = KDTree(points).query(points, k=k + 1)
    distance, neighbour = distance[:, 1:], neighbour[:, 1:]  # [N, k] without the point itself
    around = points[neighbour[:, :NORMAL_NEIGHBOURS]]  # [N, kn, 3]
    centred = around - around.mean(axis=1, keepdims=True)
    normals = smallest_eigenvectors(np.einsum("nki,nkj->nij", centred, centred))[1]  # [N, 3]
    within = distance < radius  # [N, k]
    # float32 from here: the features only choose histogram bins
    offsets = (points[neighbour] - points[:, None]).astype(np.float32)  # [N, k, 3]
    direction = offsets / np.maximum(distance[..., None], 1e-12).astype(np.float32)
    normals = normals.astype(np.float32)
    their_normals = normals[neighbour]  # [N, k, 3]
    features = (
        np.abs(direction @ normals[:, :, None])[..., 0],  # |n_p . d|
        np.abs((their_normals * direction).sum(axis=2)),  # |n_q . d|
        np.abs(their_normals @ normals[:, :, None])[..., 0],  # |n_p . n_q|
        distance / radius,
    )  # each [N, k], in [0, 1]
    width = PAIR_FEATURES * BINS
    rows = np.broadcast_to(np.arange(n)[:, None] * width, distance.shape)  # [N, k]
    counts = np.zeros(n * width)
    for f, values in enumerate(features):
        bins = np.minimum((values * BINS).astype(np.int64), BINS - 1)  # [N, k]
        counts += np.bincount((rows + f * BINS + bins)[within], minlength=n * width)
    own = (counts.reshape(n, width) / np.maximum(within.sum(axis=1, keepdims=True), 1)).astype(np.float32)
    weights = np.where(within, 1.0 / np.maximum(distance, 1e-12), 0.0)  # [N, k]
    weights = (weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)
    return own + (weights[:, None, :] @ own[neighbour])[:, 0]  # [N, width]
