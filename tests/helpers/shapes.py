"""Synthetic point clouds shared by the tests: smooth closed surfaces drawn from a seed (no dataset needed).

The same arguments give the same points, bit for bit. Functions taking ``seed`` start their own generator;
those taking ``rng`` draw from the caller's, which goes on to draw what the test needs next.

Import as ``from shapes import ...``: ``pythonpath`` in ``pyproject.toml`` puts this folder on ``sys.path``
(this folder, not ``tests/``, whose ``service``, ``model`` and ``export`` folders would shadow the packages).
"""

from __future__ import annotations

import numpy as np

from model.analytic_shapes import (  # noqa: F401  -- the shapes tests import from here
    ELLIPSOID_AXES,
    asymmetric_blob,
    bumpy_ellipsoid,
    ellipsoid_surface,
    lumpy_sphere,
    smooth_blob,
    unit_directions,
)


def sphere_shapes(count: int, points: int = 1024, seed: int = 0) -> np.ndarray:
    """Points uniform on the unit sphere, ``float32 [count, points, 3]``."""
    return unit_directions(np.random.default_rng(seed), (count, points)).astype(np.float32)


def bumpy_sphere(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n, 3)`` float64 points on a sphere with radial bumps ``0.25 sin 3θ cos 2φ + 0.1 cos 5θ``,
    squashed to semi-axes 1, 0.7, 0.5."""
    d = unit_directions(rng, n)
    theta, phi = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    radius = 1.0 + 0.25 * np.sin(3 * theta) * np.cos(2 * phi) + 0.1 * np.cos(5 * theta)
    return d * radius[:, None] * np.array([1.0, 0.7, 0.5])


def ellipsoid_and_box(
    n: int,
    seed: int,
    half: float = 0.5,
    box_scale: tuple[float, float, float] = (1.0, 1.0, 1.0),
    offset: tuple[float, float, float] = (1.5, 0.0, 0.0),
) -> np.ndarray:
    """``(n, 3)`` float64 points: ``n // 2`` on an ellipsoid surface (semi-axes 1, 0.6, 0.4) at the origin,
    the rest on the faces of the cube ``[-half, half]^3``, scaled by ``box_scale`` and moved by ``offset``."""
    rng = np.random.default_rng(seed)
    m = n - n // 2
    ellipsoid = unit_directions(rng, n // 2) * [1.0, 0.6, 0.4]
    box = rng.uniform(-half, half, size=(m, 3))
    face = rng.integers(0, 3, size=m)
    box[np.arange(m), face] = np.sign(rng.normal(size=m)) * half
    return np.concatenate([ellipsoid, box * np.asarray(box_scale) + np.asarray(offset)])


def room_scene(rng: np.random.Generator, count: int = 6000, boxes: int = 8) -> np.ndarray:
    """A box-shaped room (floor and three walls, 4 x 3 x 2.5 m) with a table: points on its surfaces."""
    floor = np.c_[rng.uniform(0, 4, count), rng.uniform(0, 3, count), np.zeros(count)]
    wall_x = np.c_[np.zeros(count), rng.uniform(0, 3, count), rng.uniform(0, 2.5, count)]
    wall_y = np.c_[rng.uniform(0, 4, count), np.zeros(count), rng.uniform(0, 2.5, count)]
    wall_x2 = np.c_[np.full(count, 4.0), rng.uniform(0, 3, count), rng.uniform(0, 2.5, count)]
    furniture = []  # the surfaces of boxes, which tell one place along the walls from another
    for _ in range(boxes):
        corner, size = rng.uniform([0.2, 0.2, 0.0], [3.4, 2.4, 0.5]), rng.uniform(0.2, 0.8, 3)
        box = corner + rng.uniform(0, 1, (count // 4, 3)) * size
        side = rng.integers(0, 3, len(box))
        box[np.arange(len(box)), side] = corner[side] + size[side] * rng.integers(0, 2, len(box))
        furniture.append(box)
    return np.concatenate([floor, wall_x, wall_y, wall_x2, *furniture])


def range_patch(points: int, seed: int = 0) -> np.ndarray:
    """``[points, 3]`` on a curved, asymmetric height field over 1 x 0.5: a range image's surface."""
    rng = np.random.default_rng(seed)
    x, y = rng.random(points), 0.5 * rng.random(points)
    return np.stack([x, y, 0.12 * np.sin(4 * x) * np.cos(5 * y) + 0.15 * x**2 + 0.05 * y], axis=1)
