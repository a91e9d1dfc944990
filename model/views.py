"""Simulated range scans: the points of a cloud that a camera sees (hidden point removal), for the ``scans`` setting.

A range scanner sees the surface facing it and nothing behind it. :func:`visible_indices` finds those points of a
sampled surface with the hidden point removal operator of Katz, Tal and Basri (SIGGRAPH 2007): seen from the
camera, each point is flipped about a large sphere (``p -> p + 2 (R - |p|) p / |p|``, ``R = 10^gamma max |p|``);
the points whose flips are vertices of the convex hull of the flips and the camera are visible. ``gamma = 2``
keeps 21-49% of a 2,048-point sample of a dense ModelNet40 test shape (unit ball) seen from 3 units off its
origin (median 32%; 34 shapes).

:func:`view_crop_indices` gives each cloud of a batch its own camera: ``keep`` of its visible points at random,
and where a view shows fewer than ``keep`` points, the hidden points nearest the camera fill the rest (counts stay
fixed within a pairs file). :func:`view_directions` draws the two cameras of each pair: the source's uniform on the
sphere, the target's turned from it by an angle uniform in ``[0, max_angle]`` about a random perpendicular axis.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

HPR_GAMMA = 2.0  # flip radius = 10^gamma x the farthest point's distance from the camera
CAMERA_DISTANCE = 3.0  # cameras stand this many shape radii from the shape's centroid


def visible_indices(points: np.ndarray, camera: np.ndarray, gamma: float = HPR_GAMMA) -> np.ndarray:
    """Ascending indices of the points of ``points [N, 3]`` seen from ``camera [3]`` (hidden point removal)."""
    rel = points.astype(np.float64) - camera  # [N, 3]
    dist = np.linalg.norm(rel, axis=1, keepdims=True)  # [N, 1]
    if not (dist > 0).all():
        raise ValueError("the camera must not coincide with a point")
    radius = dist.max() * 10.0**gamma
    flipped = rel + 2.0 * (radius - dist) * rel / dist  # [N, 3]
    hull = ConvexHull(np.vstack([flipped, np.zeros((1, 3))]))  # the camera is the origin here
    vertices = hull.vertices
    return np.sort(vertices[vertices < len(points)])


def view_directions(rng: np.random.Generator, count: int, max_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit view directions ``[count, 3]`` of the source and target cameras, the target's turned from the source's
    by an angle uniform in ``[0, max_angle_deg]``."""
    source = rng.normal(size=(count, 3))
    source /= np.linalg.norm(source, axis=1, keepdims=True)  # [count, 3] uniform on the sphere
    helper = rng.normal(size=(count, 3))
    axis = np.cross(source, helper)  # [count, 3] perpendicular to the source direction
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.deg2rad(rng.uniform(0.0, max_angle_deg, size=(count, 1)))  # [count, 1]
    target = source * np.cos(angle) + np.cross(axis, source) * np.sin(angle)  # Rodrigues, axis _|_ source
    return source, target


def view_crop_indices(
    clouds: np.ndarray, centres: np.ndarray, radii: np.ndarray, directions: np.ndarray, keep: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """What each camera sees of ``clouds [B, N, 3]``: ascending indices ``[B, keep]`` and the number of hidden
    points among them ``[B]`` (the fill where a view shows fewer than ``keep`` points).

    Camera ``b`` stands at ``centres[b] + CAMERA_DISTANCE * radii[b] * directions[b]`` (``[B, 3]``, ``[B]``,
    unit ``[B, 3]``); ``keep`` of its visible points are drawn at random.
    """
    B, N = clouds.shape[:2]
    if not 1 <= keep <= N:
        raise ValueError(f"keep must be in 1..{N}, got {keep}")
    cameras = centres + CAMERA_DISTANCE * radii[:, None] * directions  # [B, 3]
    kept, hidden_kept = np.empty((B, keep), dtype=np.int64), np.zeros(B, dtype=np.int64)
    for b in range(B):  # one convex hull per cloud
        seen = visible_indices(clouds[b], cameras[b])
        if len(seen) >= keep:
            kept[b] = np.sort(rng.choice(seen, size=keep, replace=False))
            continue
        hidden = np.setdiff1d(np.arange(N), seen)  # [N - V]
        nearest = hidden[np.argsort(np.linalg.norm(clouds[b, hidden] - cameras[b], axis=1), kind="stable")]
        kept[b] = np.sort(np.concatenate([seen, nearest[: keep - len(seen)]]))
        hidden_kept[b] = keep - len(seen)
    return kept, hidden_kept
