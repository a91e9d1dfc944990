"""Smooth closed analytic surfaces drawn from a seed (no dataset needed): round objects without symmetries, as the
tests register and as ``python -m bench.turntable_scans`` scans on a turntable.

The same arguments give the same points, bit for bit. Functions taking ``seed`` start their own generator; those
taking ``rng`` draw from the caller's.
"""

from __future__ import annotations

import numpy as np

ELLIPSOID_AXES = (1.0, 0.6, 0.8)


def unit_directions(rng: np.random.Generator, size: int | tuple[int, ...]) -> np.ndarray:
    """``[*size, 3]`` float64 unit vectors, uniform on the sphere."""
    d = rng.normal(size=(*np.atleast_1d(size), 3))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


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
