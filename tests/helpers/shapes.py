"""Synthetic point clouds shared by the tests: smooth closed surfaces drawn from a seed (no dataset needed).

The same arguments give the same points, bit for bit. Functions taking ``seed`` start their own generator;
those taking ``rng`` draw from the caller's, which goes on to draw what the test needs next.

Import as ``from shapes import ...``: ``pythonpath`` in ``pyproject.toml`` puts this folder on ``sys.path``
(this folder, not ``tests/``, whose ``service``, ``model`` and ``export`` folders would shadow the packages).
"""

from __future__ import annotations

import numpy as np

ELLIPSOID_AXES = (1.0, 0.6, 0.8)


def unit_directions(rng: np.random.Generator, size: int | tuple[int, ...]) -> np.ndarray:
    """``[*size, 3]`` float64 unit vectors, uniform on the sphere."""
    d = rng.normal(size=(*np.atleast_1d(size), 3))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def sphere_shapes(count: int, points: int = 1024, seed: int = 0) -> np.ndarray:
    """Points uniform on the unit sphere, ``float32 [count, points, 3]``."""
    return unit_directions(np.random.default_rng(seed), (count, points)).astype(np.float32)


def ellipsoid_surface(
    rng: np.random.Generator,
    size: int | tuple[int, ...],
    axes: tuple[float, float, float] = ELLIPSOID_AXES,
    bump: float = 0.15,
    random_axes: tuple[float, float] | None = None,
) -> np.ndarray:
    """``float64 [*size, 3]`` points on an ellipsoid with semi-axes ``axes``, displaced by
    ``bump * sin(3 * (y, z, x))`` (a smooth surface without symmetries; ``bump=0``: the plain ellipsoid).

    ``size = (count, points)`` gives ``count`` shapes. ``random_axes = (low, high)``: each shape's three
    semi-axes are drawn uniformly from that range (after the angles) instead of ``axes``.
    """
    u, v = rng.uniform(0, 2 * np.pi, size), rng.uniform(-1, 1, size)
    ring = np.sqrt(1 - v**2)
    if random_axes is None:
        pts = np.stack([axes[0] * ring * np.cos(u), axes[1] * ring * np.sin(u), axes[2] * v], -1)
    else:
        radii = rng.uniform(*random_axes, (*u.shape[:-1], 1, 3))
        pts = np.stack([ring * np.cos(u), ring * np.sin(u), v], -1) * radii
    if bump:
        pts = pts + bump * np.sin(3 * pts[..., [1, 2, 0]])
    return pts


def bumpy_ellipsoid(n: int, seed: int = 0, dtype: type = np.float64) -> np.ndarray:
    """``[n, 3]`` points of :func:`ellipsoid_surface` with its defaults (semi-axes 1, 0.6, 0.8; bump 0.15)."""
    return ellipsoid_surface(np.random.default_rng(seed), n).astype(dtype, copy=False)


def smooth_blob(n: int = 600, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` float32 points on a smooth, non-symmetric blob of radius ~1."""
    d = unit_directions(np.random.default_rng(seed), n)
    radius = 1 + 0.3 * d[:, :1] ** 2 + 0.2 * d[:, 1:2] * d[:, 2:3] + 0.1 * d[:, 2:3]
    return (d * radius).astype(np.float32)


def asymmetric_blob(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` float64 points on a smooth closed surface with four arms of different lengths in skew
    directions: no rotational symmetry, so exactly one rotation aligns it with itself."""
    d = unit_directions(np.random.default_rng(seed), n)  # [n, 3]
    arms = np.array([[1, 0.2, 0.1], [-0.3, 1, 0.2], [-0.4, -0.5, 1], [-0.6, -0.7, -0.6]])
    arms /= np.linalg.norm(arms, axis=1, keepdims=True)  # [4, 3]
    length = np.array([0.9, 0.6, 0.4, 0.25])
    radius = 0.6 + (length * np.clip(d @ arms.T, 0, None) ** 4).sum(1)  # [n]
    return d * radius[:, None]


def lumpy_sphere(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` float64 points on a unit sphere carrying 40 Gaussian lumps and dents (heights -0.15-0.15, widths
    0.15-0.35) at fixed places: every patch looks different, as a scanned object's surface does (rotation-invariant
    descriptors need that), and no rotation maps it onto itself. ``seed`` draws the points only."""
    centres = unit_directions(np.random.default_rng(100), 40)  # [40, 3] the same lumps for every seed
    heights = np.random.default_rng(101).uniform(-0.15, 0.15, 40)  # [40]
    widths = np.random.default_rng(102).uniform(0.15, 0.35, 40)  # [40]
    d = unit_directions(np.random.default_rng(seed), n)  # [n, 3]
    radius = 1 + (heights * np.exp(-((d[:, None] - centres[None]) ** 2).sum(2) / widths**2)).sum(1)  # [n]
    return d * radius[:, None]


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
