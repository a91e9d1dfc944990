"""The partial-view check of rotation_search="auto" (service.stages.partial) and service.quality.near_surface_share."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob, ellipsoid_surface

from service.manifest import bundled_models_dir
from service.quality import near_surface_share
from service.registrar import Registrar
from service.stages.normalise import normalise
from service.stages.partial import half_turns, looks_partial
from service.stages.sample import sample
from service.stages.validate import validate

BUNDLED = bundled_models_dir() / "general"


def plane(x_range: tuple[float, float], spacing: float = 0.02) -> np.ndarray:
    """``[N, 3]`` grid points of the plane z = 0 over ``x_range`` x [0, 1]."""
    x, y = np.meshgrid(np.arange(*x_range, spacing), np.arange(0.0, 1.0, spacing))
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def test_a_partial_view_in_place_is_near_the_surface_and_a_crossing_pose_is_not() -> None:
    target, source = plane((0.0, 2.0)), plane((1.0, 3.0))  # half of the source lies beyond the target
    in_place = near_surface_share(source, target, np.eye(3), np.zeros(3), 0.05)
    turn = Rotation.from_euler("y", 20.0, degrees=True).as_matrix()
    centre = np.array([1.5, 0.5, 0.0])
    crossing = near_surface_share(source, target, turn, centre - turn @ centre, 0.05)
    # measured 0.91 (the source's points just beyond the target's edge are near, not on it) and 0.35
    assert in_place > 0.85 and crossing < 0.5, (in_place, crossing)
    assert near_surface_share(source + 10.0, target, np.eye(3), np.zeros(3), 0.05) == 0.0  # nothing near


def test_half_turns_turn_the_pose_180_degrees_about_the_moved_points_centroid() -> None:
    points = asymmetric_blob(400, 1)
    R, t = Rotation.from_euler("zyx", [30.0, 10.0, -20.0], degrees=True).as_matrix(), np.array([0.3, -0.2, 1.0])
    R_h, t_h = half_turns(points, R, t)
    centre = (points @ R.T + t).mean(axis=0)
    for R_i, t_i in zip(R_h, t_h, strict=True):
        assert Rotation.from_matrix(R_i @ R.T).magnitude() == pytest.approx(np.pi)
        np.testing.assert_allclose((points @ R_i.T + t_i).mean(axis=0), centre, atol=1e-12)


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    if not (BUNDLED / "manifest.json").exists():
        pytest.skip("bundled model 'general' absent")
    return Registrar(BUNDLED, threads=1)


def working(registrar: Registrar, source: np.ndarray, target: np.ndarray):
    request = validate(source, target, None, {}, registrar.default_iterations, registrar.default_keypoints)
    return request, normalise(sample(request), registrar.reference_radius)


def as_result(registrar: Registrar, request, work, R: np.ndarray, t: np.ndarray):
    """The plain pass's result of ``request`` with its pose replaced by ``R, t``."""
    return dataclasses.replace(registrar.solve(work, request, None, {}), rotation=R, translation=t)


def test_the_right_pose_of_a_partial_view_looks_partial_and_a_half_turn_does_not(registrar) -> None:
    shape = asymmetric_blob(4000, 2)
    source, target = shape[shape[:, 0] < 0.3], shape[shape[:, 0] > -0.3]  # overlapping halves
    request, work = working(registrar, source, target)
    assert looks_partial(work, as_result(registrar, request, work, np.eye(3), np.zeros(3)))
    R_h, t_h = half_turns(source, np.eye(3), np.zeros(3))
    assert not looks_partial(work, as_result(registrar, request, work, R_h[0], t_h[0]))


def test_a_pose_whose_half_turn_fits_as_well_is_not_taken_for_a_partial_view(registrar) -> None:
    shape = ellipsoid_surface(np.random.default_rng(3), 4000, bump=0.0)  # symmetric about its three axes
    source, target = shape[shape[:, 0] < 0.4], shape[shape[:, 0] > -0.4]
    request, work = working(registrar, source, target)
    R, t = np.eye(3), np.zeros(3)
    assert near_surface_share(work.working_source, work.tgt_w, R, t, work.inlier_distance) >= 0.75
    assert not looks_partial(work, as_result(registrar, request, work, R, t))  # its half turn about x fits too
