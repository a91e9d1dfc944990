"""Sensor simulation (model.sensor_sim): normals, range-image density, range noise, flying pixels, the returns of a
pixel grid, one scan."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from shapes import sphere_shapes

from model.sensor_sim import (
    SensorEffects,
    camera_axes,
    densify,
    estimate_normals,
    in_frustum,
    mixed_pixels,
    orient_to_camera,
    pixel_grid_returns,
    pixel_rays,
    range_image_keep_probability,
    range_noise,
    scan,
)


def square(rng: np.random.Generator, n: int, half: float, z: float) -> np.ndarray:
    """``[n, 3]`` uniform points on the square ``[-half, half]^2`` at height ``z``."""
    return np.c_[rng.uniform(-half, half, (n, 2)), np.full(n, z)]


def test_normals_of_a_plane_are_its_axis_and_turn_to_the_camera() -> None:
    points = square(np.random.default_rng(0), 800, 1.0, 0.0)
    normals = estimate_normals(points)
    assert np.allclose(np.abs(normals[:, 2]), 1.0, atol=1e-6)
    below = orient_to_camera(normals, points, np.array([0.3, 0.0, -2.0]))
    assert (below[:, 2] < 0).all()
    assert (orient_to_camera(normals, points, np.array([0.0, 0.0, 2.0]))[:, 2] > 0).all()


def test_normals_of_a_sphere_are_radial() -> None:
    sphere = sphere_shapes(1, 2048, seed=1)[0].astype(np.float64)
    cos = np.abs(np.einsum("ni,ni->n", estimate_normals(sphere), sphere))
    assert np.median(cos) > 0.99 and cos.min() > 0.9


def test_densify_adds_points_on_the_surface_and_keeps_the_originals() -> None:
    sphere = sphere_shapes(1, 1024, seed=2)[0].astype(np.float64)
    points, normals = densify(sphere, sphere.copy(), 4, np.random.default_rng(0))
    assert points.shape == normals.shape == (4096, 3)
    assert np.array_equal(points[:1024], sphere)
    radius = np.linalg.norm(points[1024:], axis=1)
    assert radius.max() <= 1.0 + 1e-9 and np.quantile(radius, 0.01) > 0.97  # chords of nearby points


def test_range_image_density_falls_with_the_incidence_angle() -> None:
    """On a sphere seen from far away (no distance fall-off), the kept share follows |cos(normal, ray)|."""
    rng = np.random.default_rng(3)
    sphere = sphere_shapes(1, 20000, seed=3)[0].astype(np.float64)
    camera = np.array([0.0, 0.0, 50.0])
    probability = range_image_keep_probability(sphere, sphere, camera, distance_power=0.0, floor=0.0)
    kept = rng.random(len(sphere)) < probability
    rays = (sphere - camera) / np.linalg.norm(sphere - camera, axis=1, keepdims=True)
    cos = np.abs(np.einsum("ni,ni->n", rays, sphere))
    facing = sphere[:, 2] > 0
    shares = [kept[facing & (cos >= lo) & (cos < lo + 0.2)].mean() for lo in (0.0, 0.2, 0.4, 0.6, 0.8)]
    assert np.all(np.diff(shares) > 0.1), shares
    assert abs(shares[-1] - 0.9) < 0.05 and abs(shares[0] - 0.1) < 0.05, shares


def test_range_image_density_falls_with_the_squared_distance() -> None:
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 4.0]])
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    p = range_image_keep_probability(points, normals, np.zeros(3), distance_power=2.0, floor=0.0)
    assert np.allclose(p, [1.0, 0.25, 0.0625])
    assert range_image_keep_probability(points, normals, np.zeros(3), floor=0.1).min() == 0.1


def test_range_noise_moves_points_along_their_rays_in_proportion_to_distance() -> None:
    rng = np.random.default_rng(4)
    camera = np.array([1.0, -2.0, 0.5])
    directions = rng.normal(size=(40000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    dist = np.where(np.arange(40000) < 20000, 1.0, 4.0)[:, None]
    points = camera + directions * dist
    moved = range_noise(points, camera, 0.01, rng)
    step = moved - points
    assert np.allclose(np.cross(step, directions), 0.0, atol=1e-12)  # along the ray only
    along = np.einsum("ni,ni->n", step, directions)
    assert abs(along[:20000].std() - 0.01) < 0.0005 and abs(along[20000:].std() - 0.04) < 0.002
    assert abs(along.mean()) < 0.001


def test_flying_pixels_lie_on_rays_between_a_near_edge_and_the_surface_behind_it() -> None:
    rng = np.random.default_rng(5)
    near, far = square(rng, 2000, 0.3, 1.0), square(rng, 20000, 1.5, 0.0)
    camera = np.array([0.0, 0.0, 3.0])
    far = far[np.abs(far[:, :2] * 2 / 3).max(axis=1) > 0.3]  # what the near square hides is not in the view
    flying = mixed_pixels(np.vstack([near, far]), camera, 100, rng)
    assert 10 <= len(flying) <= 100
    assert (flying[:, 2] < 1.0).all() and (flying[:, 2] > 0.0).all()  # strictly between the two surfaces
    # where the ray of a flying point crosses the near square's plane: at its edge
    crossing = camera + (flying - camera) * ((camera[2] - 1.0) / (camera[2] - flying[:, 2]))[:, None]
    edge = np.abs(crossing[:, :2]).max(axis=1)
    assert (np.abs(edge - 0.3) < 0.06).all(), edge
    assert len(mixed_pixels(far, camera, 100, rng)) == 0  # one smooth surface: no discontinuity
    assert len(mixed_pixels(far, camera, 0, rng)) == 0


def test_frustum_keeps_the_cone_of_view() -> None:
    points = np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [5.0, 0.0, 1.0], [0.0, 0.0, -5.0]])
    inside = in_frustum(points, np.zeros(3), np.array([0.0, 0.0, 1.0]), 30.0)
    assert inside.tolist() == [True, True, False, False]


def test_a_scan_sees_the_facing_side_thinned_at_grazing_angles_and_is_seeded() -> None:
    sphere = sphere_shapes(1, 8000, seed=6)[0].astype(np.float64)
    camera = np.array([0.0, 0.0, 4.0])
    effects = SensorEffects(distance_power=0.0, density_floor=0.0, relative_noise=0.0, mixed_share=0.0)
    seen = scan(sphere, sphere, camera, np.array([0.0, 0.0, -1.0]), effects, np.random.default_rng(7))
    assert (seen[:, 2] > 0.0).all()  # nothing on the far side
    assert np.mean(seen[:, 2] > 0.25) > 0.95  # the horizon from 4 radii is at z = 1/4
    assert 0.1 * 8000 < len(seen) < 0.3 * 8000  # a cap of 3/8 of the sphere, thinned by |cos|
    middle, rim = (seen[:, 2] > 0.8).sum() / (sphere[:, 2] > 0.8).sum(), \
        ((seen[:, 2] > 0.25) & (seen[:, 2] < 0.45)).sum() / ((sphere[:, 2] > 0.25) & (sphere[:, 2] < 0.45)).sum()
    assert middle > 1.5 * rim
    again = scan(sphere, sphere, camera, np.array([0.0, 0.0, -1.0]), effects, np.random.default_rng(7))
    assert np.array_equal(seen, again)


def plane_sample(rng: np.random.Generator, n: int, half: float, tilt_deg: float, depth: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``n`` uniform points on a square of side ``2 half`` centred ``depth`` below the origin on z, turned by
    ``tilt_deg`` about x, and its normals ``[n, 3]``."""
    turn = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    points = square(rng, n, half, 0.0) @ turn.T + [0.0, 0.0, -depth]
    return points, np.tile(turn[:, 2], (n, 1))


LOOK_DOWN = np.array([0.0, 0.0, -1.0])
PITCH = 0.004


def test_pixel_grid_returns_lie_one_per_pixel_on_the_rays_of_the_grid_and_cover_a_facing_plane() -> None:
    points, normals = plane_sample(np.random.default_rng(8), 40_000, 0.5, 0.0, 2.0)
    returns = pixel_grid_returns(points, normals, np.zeros(3), LOOK_DOWN, PITCH)
    local = returns @ camera_axes(LOOK_DOWN).T  # [M, 3] right, up, depth
    np.testing.assert_allclose(local[:, 2], 2.0, atol=1e-9)  # on the plane
    pixel = local[:, :2] / local[:, 2:] / PITCH - 0.5  # integer where a return lies on its pixel's ray
    np.testing.assert_allclose(pixel, np.round(pixel), atol=1e-6)
    assert len(np.unique(np.round(pixel), axis=0)) == len(returns)  # one return per pixel
    inner = (np.abs(local[:, :2]) < 0.45).all(axis=1).sum()  # away from the square's edge: hardly a pixel left empty
    assert 0.999 * (2 * round(0.45 / 2.0 / PITCH)) ** 2 <= inner <= (2 * round(0.45 / 2.0 / PITCH)) ** 2, inner
    centre_ray = np.array([PITCH / 2, PITCH / 2, 1.0])
    np.testing.assert_allclose(pixel_rays(np.zeros((1, 2)), PITCH)[0], centre_ray / np.linalg.norm(centre_ray))


def test_pixel_grid_returns_thin_with_the_incidence_angle_and_the_squared_distance() -> None:
    rng = np.random.default_rng(9)
    def per_area(tilt_deg: float, depth: float) -> float:
        points, normals = plane_sample(rng, 40_000, 0.5, tilt_deg, depth)
        return len(pixel_grid_returns(points, normals, np.zeros(3), LOOK_DOWN, PITCH)) / 1.0  # the square's area: 1

    facing = per_area(0.0, 3.0)
    assert abs(per_area(60.0, 3.0) / facing - 0.5) < 0.05  # cos 60 deg
    assert abs(per_area(0.0, 6.0) / facing - 0.25) < 0.02  # twice as far


def test_a_hidden_surface_returns_nothing_and_a_scan_on_the_pixel_grid_is_seeded() -> None:
    rng = np.random.default_rng(10)
    near, near_normals = plane_sample(rng, 10_000, 0.2, 0.0, 1.0)
    far, far_normals = plane_sample(rng, 40_000, 1.0, 0.0, 2.0)
    points, normals = np.vstack([near, far]), np.vstack([near_normals, far_normals])
    returns = pixel_grid_returns(points, normals, np.zeros(3), LOOK_DOWN, PITCH)
    on_far = returns[np.abs(returns[:, 2] + 2.0) < 1e-6]
    behind_near = (np.abs(on_far[:, :2] / 2.0) < 0.2 - 2 * PITCH).all(axis=1)  # the near square's shadow
    assert len(on_far) > 0 and not behind_near.any()
    effects = SensorEffects(relative_noise=0.001, mixed_share=0.01, pixel_pitch=PITCH)
    scanned = scan(points, normals, np.zeros(3), LOOK_DOWN, effects, np.random.default_rng(11))
    assert len(returns) <= len(scanned) <= 1.02 * len(returns)  # the returns and flying pixels at the near edge
    assert np.array_equal(scanned, scan(points, normals, np.zeros(3), LOOK_DOWN, effects, np.random.default_rng(11)))
