"""What a range sensor does to a surface sample: one small function per effect, composed by :func:`scan`.

* :func:`estimate_normals` -- unoriented normals by local PCA; :func:`orient_to_camera` turns them to a camera.
* :func:`densify` -- more points on a sparse sample's surface (random points in the triangles a point forms with
  two of its nearest neighbours), so that a view still holds enough points after thinning.
* :func:`in_frustum` -- the points inside a camera's cone of view.
* :func:`range_image_keep_probability` -- a range image samples the surface on a grid of rays, so its surface
  density falls with the incidence angle (``|cos|`` of normal and view ray) and with the squared distance; a
  point is kept with that relative density.
* :func:`range_noise` -- noise along the view ray, its sigma proportional to the distance.
* :func:`mixed_pixels` -- boundary artefacts: at depth discontinuities a pixel mixes the foreground and the
  background depth, giving points strung along the ray between the two surfaces ("flying pixels").
* :func:`pixel_grid_returns` -- what a range camera's grid of rays returns of a surface sample: each ray through a
  pixel centre meets the nearest of the sample's surfels (discs on its tangent planes), so the returns lie on the
  pixel grid, a hidden surface returns nothing and the density on the surface falls with the incidence angle and the
  squared distance, as a real range image's does, without the clumps and gaps of random thinning.
* :func:`scan` -- frustum, then either density thinning and hidden point removal (:func:`model.views.visible_indices`)
  or, where ``SensorEffects.pixel_pitch`` is set, :func:`pixel_grid_returns`; then artefacts and noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from model.views import visible_indices

NORMAL_NEIGHBOURS = 12  # points of the local PCA behind each normal (the point itself included)
SURFEL_SPACINGS = 3.5  # a surfel's radius, in median nearest-neighbour spacings: holes under 0.1% of a uniform sample
SURFEL_CHUNK = 50_000  # surfels splatted at once (bounds the memory of pixel_grid_returns)


def estimate_normals(points: np.ndarray, k: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normals ``[N, 3]`` of ``points [N, 3]``: the least-variance axis of each point's ``k`` nearest points."""
    k = min(k, len(points))
    _, nn = cKDTree(points).query(points, k)  # [N, k]
    nbr = points[nn]  # [N, k, 3]
    centred = nbr - nbr.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred)  # [N, 3, 3]
    return np.linalg.eigh(cov)[1][:, :, 0]  # eigenvalues ascend: column 0 is the normal


def orient_to_camera(normals: np.ndarray, points: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """``normals [N, 3]`` flipped where needed so that each faces ``camera [3]`` (``n . (camera - p) >= 0``)."""
    facing = np.einsum("ni,ni->n", normals, camera - points) >= 0  # [N]
    return np.where(facing[:, None], normals, -normals)


def densify(points: np.ndarray, normals: np.ndarray, factor: int, rng: np.random.Generator,
            k: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``points [N, 3]`` and ``factor - 1`` new points per point (``[factor N, 3]``, the originals first), each
    uniform in the triangle of a point and two of its ``k - 1`` nearest neighbours; new points take their base
    point's normal (``normals [N, 3]`` -> ``[factor N, 3]``)."""
    if factor <= 1:
        return points, normals
    n = len(points)
    _, nn = cKDTree(points).query(points, min(k, n))  # [N, k]
    base = np.repeat(np.arange(n), factor - 1)  # [M]
    pick = np.argsort(rng.random((len(base), nn.shape[1] - 1)), axis=1)[:, :2] + 1  # [M, 2] two distinct neighbours
    a, b = nn[base, pick[:, 0]], nn[base, pick[:, 1]]  # [M] each
    u, v = rng.random((2, len(base), 1))
    flip = (u + v) > 1  # fold the square onto the triangle: uniform in the triangle
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    new = points[base] + u * (points[a] - points[base]) + v * (points[b] - points[base])  # [M, 3]
    return np.vstack([points, new]), np.vstack([normals, normals[base]])


def in_frustum(points: np.ndarray, camera: np.ndarray, look: np.ndarray, half_angle_deg: float) -> np.ndarray:
    """Mask ``[N]``: the points within ``half_angle_deg`` of the camera's unit viewing direction ``look [3]``."""
    rel = points - camera  # [N, 3]
    cos = rel @ look / np.maximum(np.linalg.norm(rel, axis=1), 1e-12)
    return cos >= np.cos(np.deg2rad(half_angle_deg))


def range_image_keep_probability(points: np.ndarray, normals: np.ndarray, camera: np.ndarray,
                                 distance_power: float = 2.0, floor: float = 0.02) -> np.ndarray:
    """Probability ``[N]`` of keeping each point of a dense, uniform sample so that the rest has the surface
    density of a range image: ``|cos(normal, ray)| * (d_min / d) ** distance_power``, at least ``floor``."""
    rel = points - camera  # [N, 3]
    dist = np.linalg.norm(rel, axis=1)  # [N]
    cos = np.abs(np.einsum("ni,ni->n", normals, rel)) / np.maximum(dist, 1e-12)
    return np.clip(cos * (dist.min() / dist) ** distance_power, floor, 1.0)


def range_noise(points: np.ndarray, camera: np.ndarray, relative_sigma: float,
                rng: np.random.Generator) -> np.ndarray:
    """``points [N, 3]`` moved along their view rays by Gaussian noise of sigma ``relative_sigma * distance``."""
    rel = points - camera  # [N, 3]
    dist = np.linalg.norm(rel, axis=1, keepdims=True)  # [N, 1]
    return points + rel / dist * (relative_sigma * dist * rng.standard_normal((len(points), 1)))


def mixed_pixels(points: np.ndarray, camera: np.ndarray, count: int, rng: np.random.Generator,
                 relative_jump: float = 0.05, neighbours: int = 8) -> np.ndarray:
    """Up to ``count`` flying points ``[M, 3]`` at the depth discontinuities of a view ``points [N, 3]``.

    A point is on a discontinuity where one of its ``neighbours`` nearest in viewing direction lies deeper by more
    than ``relative_jump`` times its own distance; the flying point sits on its ray at a depth uniform between its
    own and that neighbour's (a pixel mixing the foreground and the background)."""
    if count <= 0 or len(points) < 2:
        return np.empty((0, 3))
    rel = points - camera
    dist = np.linalg.norm(rel, axis=1)  # [N]
    rays = rel / dist[:, None]  # [N, 3] unit
    _, nn = cKDTree(rays).query(rays, min(neighbours, len(points)))  # [N, k] nearest in direction
    deeper = dist[nn].max(axis=1)  # [N]
    edge = np.flatnonzero(deeper - dist > relative_jump * dist)
    if len(edge) == 0:
        return np.empty((0, 3))
    chosen = rng.choice(edge, size=min(count, len(edge)), replace=False)
    depth = dist[chosen] + rng.uniform(0.1, 0.9, len(chosen)) * (deeper[chosen] - dist[chosen])
    return camera + rays[chosen] * depth[:, None]


def camera_axes(look: np.ndarray) -> np.ndarray:
    """``[3, 3]`` rows: the image's right and up axes and the unit viewing direction along ``look [3]`` (up is the
    world's z as far as ``look`` allows, else its y)."""
    forward = look / np.linalg.norm(look)
    world_up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, world_up)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(right, forward), forward])


def pixel_rays(pixels: np.ndarray, pitch: float) -> np.ndarray:
    """``[..., 3]`` unit rays in the camera's axes through the centres of ``pixels [..., 2]`` (integer columns and
    rows) of ``pitch`` on the image plane at unit depth."""
    rays = np.concatenate([(pixels + 0.5) * pitch, np.ones((*pixels.shape[:-1], 1))], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def pixel_grid_returns(points: np.ndarray, normals: np.ndarray, camera: np.ndarray, look: np.ndarray,
                       pitch: float) -> np.ndarray:
    """``[M, 3]``: one return per pixel whose ray meets the surface of a dense sample ``points [N, 3]`` with unit
    ``normals [N, 3]``, seen from ``camera [3]`` along ``look [3]``.

    Pixels are squares of ``pitch`` on the image plane at unit depth (about ``pitch`` radians near the centre). Each
    point is a surfel: a disc of ``SURFEL_SPACINGS`` median nearest-neighbour spacings on its tangent plane. A pixel's
    ray meets every disc it passes through; the nearest meeting is its return (a depth buffer), so the returns lie on
    the rays of the pixel grid and a hidden surface returns nothing. Each disc is tried on the pixels within its radius
    at the nearest point's depth: meant for a surface well in front of the camera (a point much nearer widens that
    window for every disc)."""
    axes = camera_axes(look)  # [3, 3]
    local = (points - camera) @ axes.T  # [N, 3]: right, up, depth
    front = np.flatnonzero(local[:, 2] > 1e-9)
    if len(front) < 2:
        return np.empty((0, 3))
    radius = SURFEL_SPACINGS * float(np.median(cKDTree(points[front]).query(points[front], 2)[0][:, 1]))
    reach = int(np.ceil(radius / local[front, 2].min() / pitch))  # pixels a disc reaches from its centre's
    offsets = np.stack(np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1)), -1).reshape(-1, 2)
    centre_pixel = np.floor(local[front, :2] / local[front, 2:] / pitch).astype(np.int64)  # [F, 2]
    met_pixels, met_depths = [], []
    for start in range(0, len(front), SURFEL_CHUNK):
        index = front[start:start + SURFEL_CHUNK]  # [S]
        pixels = centre_pixel[start:start + SURFEL_CHUNK, None, :] + offsets  # [S, O, 2] pixels about each disc
        rays = pixel_rays(pixels, pitch)  # [S, O, 3]
        normal = normals[index] @ axes.T  # [S, 3] in the camera's axes
        with np.errstate(divide="ignore", invalid="ignore"):  # a ray along the disc's plane never meets it
            depth = np.einsum("si,si->s", local[index], normal)[:, None] / np.einsum("soi,si->so", rays, normal)
            meets = np.linalg.norm(rays * depth[..., None] - local[index, None, :], axis=-1) <= radius  # [S, O]
        meets &= np.isfinite(depth) & (depth > 0)
        met_pixels.append(pixels[meets])
        met_depths.append(depth[meets])
    pixels, depths = np.concatenate(met_pixels), np.concatenate(met_depths)  # [K, 2], [K]
    if len(depths) == 0:
        return np.empty((0, 3))
    order = np.lexsort((depths, pixels[:, 1], pixels[:, 0]))  # by pixel, the nearest meeting first
    pixels, depths = pixels[order], depths[order]
    nearest = np.ones(len(depths), dtype=bool)
    nearest[1:] = np.any(pixels[1:] != pixels[:-1], axis=1)
    returns = pixel_rays(pixels[nearest], pitch) * depths[nearest, None]  # [M, 3] in the camera's axes
    return camera + returns @ axes


@dataclass(frozen=True)
class SensorEffects:
    """How one scan degrades the surface (:func:`scan`)."""

    half_angle_deg: float = 180.0  # cone of view (180: everything)
    distance_power: float = 2.0  # surface density ~ d^-power (2: one range image; fused fragments nearer 0)
    density_floor: float = 0.02  # least keep probability (grazing surfaces still return a few points)
    relative_noise: float = 0.002  # range noise sigma / distance
    mixed_share: float = 0.01  # flying points added at depth discontinuities, as a share of the kept points
    pixel_pitch: float | None = None  # a range camera's pixel (radians): returns on its pixel grid, not thinning


def scan(points: np.ndarray, normals: np.ndarray, camera: np.ndarray, look: np.ndarray, effects: SensorEffects,
         rng: np.random.Generator) -> np.ndarray:
    """What a range sensor at ``camera [3]`` looking along unit ``look [3]`` returns of a dense surface sample
    ``points [N, 3]`` with ``normals [N, 3]`` (uniform where ``effects`` thins it): ``[M, 3]`` points (M varies)."""
    idx = np.flatnonzero(in_frustum(points, camera, look, effects.half_angle_deg)) if effects.half_angle_deg < 180 \
        else np.arange(len(points))
    if len(idx) == 0:
        return np.empty((0, 3))
    if effects.pixel_pitch is not None:
        pts = pixel_grid_returns(points[idx], normals[idx], camera, look, effects.pixel_pitch)
    else:
        # thinning does not depend on what hides what, so it comes first: the hull then has fewer points
        keep = rng.random(len(idx)) < range_image_keep_probability(points[idx], normals[idx], camera,
                                                                   effects.distance_power, effects.density_floor)
        idx = idx[keep]
        if len(idx) > 3:
            idx = idx[visible_indices(points[idx], camera)]
        pts = points[idx]
    flying = mixed_pixels(pts, camera, round(effects.mixed_share * len(pts)), rng)
    pts = np.vstack([pts, flying])
    return range_noise(pts, camera, effects.relative_noise, rng)
