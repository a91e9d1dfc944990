"""Clouds resampled on their own surface: the point spacing of a cloud, and a cloud made denser on its surface.

The set's RGB-D fragments were fused on 2.5 cm voxels (15,000-25,000 points each); users send full-resolution
fragments of 260,000-350,000 points. :func:`densified` draws that many points on the same surface (each point's
tangent disc), so that the service and FPFH + RANSAC + ICP can be measured at the sizes users send, on real geometry
(``python -m bench.real_scans --densify 300000``). The extra points are made up: they carry the fragment's shape, not
a sensor's noise at full resolution, which a fused fragment smooths anyway.
"""

from __future__ import annotations

import numpy as np

from service.icp import target_normals
from service.kdtree import KDTree

DISC_SHARE = 0.6  # the tangent disc's radius, a share of the cloud's spacing: discs of neighbours overlap
NOISE_SHARE = 0.1  # Gaussian noise along each normal, a share of the spacing (a fused surface is smooth)
FUSED_SENSORS = ("kinect-fused-2.5cm", "xtion-fused-2.5cm")  # the set's voxel-reduced fragments (its README)


def point_spacing(points: np.ndarray, samples: int = 2000) -> float:
    """The median distance from up to ``samples`` evenly spaced points of ``points [N, 3]`` to their nearest other."""
    probe = points[:: max(1, len(points) // samples)]
    return float(np.median(KDTree(points).query(probe, k=2)[0][:, 1]))


def densified(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``[count, 3]`` float32 points on the surface of ``points [N, 3]`` (``count >= N``): each point stands for
    ``count // N`` or one more, drawn uniformly on its tangent disc (its PCA plane,
    :func:`service.icp.target_normals`; radius ``DISC_SHARE`` of :func:`point_spacing`) and moved along its normal by
    Gaussian noise of ``NOISE_SHARE`` of the spacing. Points without a plane (a line, a lone point) stay where they
    are, with the same noise in every direction."""
    source = np.asarray(points, dtype=np.float64)  # [N, 3]
    n = len(source)
    if count < n:
        raise ValueError(f"count must be at least the {n} points given, got {count}")
    spacing = point_spacing(source)
    normals, defined = target_normals(source)  # [N, 3], [N]
    parents = np.concatenate([np.repeat(np.arange(n), count // n), rng.choice(n, count % n, replace=False)])  # [C]
    normal = normals[parents]  # [C, 3]
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])  # [C, 3] not along it
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)  # [C, 3] unit, in the tangent plane
    v = np.cross(normal, u)  # [C, 3]
    radius = DISC_SHARE * spacing * np.sqrt(rng.random(count))  # [C] uniform over the disc's area
    angle = rng.uniform(0.0, 2.0 * np.pi, count)  # [C]
    in_plane = radius[:, None] * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v)  # [C, 3]
    in_plane[~defined[parents]] = 0.0
    noise = rng.normal(0.0, NOISE_SHARE * spacing, (count, 3))  # [C, 3]
    along = np.where(defined[parents, None], (noise * normal).sum(axis=1, keepdims=True) * normal, noise)  # [C, 3]
    return (source[parents] + in_plane + along).astype(np.float32)
