"""refine_plane_many: refine_plane's two stages from many starts at once give each start refine_plane's pose."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob, room_scene

from service.icp import Surface, refine_plane
from service.icp_batch import refine_plane_many, rotations_of


def starts(count: int, seed: int, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """``count`` start poses: half a few degrees off the identity, half anywhere; translations ``spread`` off."""
    rng = np.random.default_rng(seed)
    near = Rotation.from_rotvec(rng.normal(scale=0.15, size=(count // 2, 3))).as_matrix()
    far = Rotation.random(count - count // 2, random_state=seed).as_matrix()
    return np.concatenate([near, far]), rng.normal(scale=spread, size=(count, 3))


def one_at_a_time(src, tgt, R0, t0, distance: float, iterations: int, target: Surface, source: Surface):
    results = [refine_plane(src, tgt, R, t, max_distance=distance, max_iterations=iterations, target_surface=target,
                            source_surface=source) for R, t in zip(R0, t0, strict=True)]
    return np.stack([r.rotation for r in results]), np.stack([r.translation for r in results])


@pytest.mark.parametrize("iterations", [1, 3, 10])
def test_every_start_gets_the_pose_refine_plane_gives_it(iterations) -> None:
    src = asymmetric_blob(600, 0)
    tgt = asymmetric_blob(700, 1) @ Rotation.from_euler("z", 8, degrees=True).as_matrix().T + 0.02
    target, source = Surface.of(tgt), Surface.of(src)
    R0, t0 = starts(16, 0, 0.05)
    R, t = refine_plane_many(src, tgt, R0, t0, max_distance=0.1, max_iterations=iterations, target=target,
                             source=source)
    R_one, t_one = one_at_a_time(src, tgt, R0, t0, 0.1, iterations, target, source)
    np.testing.assert_allclose(R, R_one, atol=1e-9)
    np.testing.assert_allclose(t, t_one, atol=1e-9)
    assert np.abs(R - R0).max() > 0.01  # the starts moved


def test_starts_without_pairs_stay_and_planar_ones_continue_point_to_point_as_refine_plane_does() -> None:
    rng = np.random.default_rng(3)
    room = room_scene(rng, 3000)
    floor = room[np.abs(room[:, 2] - room[:, 2].min()) < 1e-6][:400]  # a plane: point-to-plane is degenerate there
    assert len(floor) > 100
    for src, tgt in ((room[::5], room[1::5]), (floor, floor + np.array([0.01, 0.0, 0.0]))):
        target, source = Surface.of(tgt), Surface.of(src)
        R0, t0 = starts(8, 1, 0.05)
        t0[-1] = 100.0  # far from everything: no pair, the start is returned as it is
        R, t = refine_plane_many(src, tgt, R0, t0, max_distance=0.1, max_iterations=5, target=target, source=source)
        R_one, t_one = one_at_a_time(src, tgt, R0, t0, 0.1, 5, target, source)
        np.testing.assert_allclose(R, R_one, atol=1e-9)
        np.testing.assert_allclose(t, t_one, atol=1e-9)
        np.testing.assert_array_equal(t[-1], t0[-1])


def test_rotations_of_matches_scipy_including_tiny_angles() -> None:
    rotvec = np.array([[0.3, -0.2, 0.1], [1e-10, 0.0, -2e-10], [0.0, 0.0, 0.0], [np.pi, 0.0, 0.0]])
    R = rotations_of(rotvec, np.linalg.norm(rotvec, axis=1))
    np.testing.assert_allclose(R, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)


def test_wrongly_shaped_starts_are_refused() -> None:
    cloud = asymmetric_blob(100, 0)
    surface = Surface.of(cloud)
    with pytest.raises(ValueError, match="R0 must be"):
        refine_plane_many(cloud, cloud, np.eye(3), np.zeros(3), max_distance=0.1, max_iterations=3, target=surface,
                          source=surface)
