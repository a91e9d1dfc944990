"""Specification of ``service.stability``: how firmly the geometry pins a registered pose down."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob, ellipsoid_surface

from service.icp import Surface
from service.kdtree import KDTree
from service.registrar import Registrar
from service.stability import PINNED_RATIO, WEAK_EIGENVALUE, Stability, pose_stability, weak_motion_warning

BUNDLED = Path(__file__).resolve().parents[2] / "service" / "models" / "general"
SPHEROID_AXES = (0.6, 0.6, 1.0)  # a solid of revolution about z


def spheroid(n: int, seed: int) -> np.ndarray:
    return ellipsoid_surface(np.random.default_rng(seed), n, axes=SPHEROID_AXES, bump=0.0)


def stability_of(source: np.ndarray, target: np.ndarray, max_distance: float = 0.1) -> Stability | None:
    """Stability of ``source`` on ``target`` at the identity pose (two samples of one surface)."""
    return pose_stability(source, target, KDTree(target), max_distance)


def test_a_shape_of_revolution_turns_freely_about_its_axis() -> None:
    stability = stability_of(spheroid(800, 0), spheroid(800, 1))
    assert stability is not None and stability.weak
    assert abs(stability.motion[2]) > 0.95  # the weak motion is a turn about z
    warning = weak_motion_warning(stability)
    assert warning.startswith("weakly constrained: a turn about the axis")
    assert "symmetric" in warning


def test_the_turn_axis_of_a_part_of_a_shape_of_revolution_is_its_axis() -> None:
    """The least constrained turn of a part away from the axis is about the axis itself, not the part's centroid."""
    offset = np.array([0.4, -0.2, 0.3])
    part = spheroid(2000, 0)
    part = part[part[:, 0] > 0.2] + offset  # [P, 3]: one side of the spheroid, its axis through ``offset``
    stability = stability_of(part, spheroid(2000, 1) + offset)
    point, direction = stability.turn_axis()
    assert abs(direction[2]) > 0.99
    off_axis = (point - offset) - ((point - offset) @ direction) * direction
    assert np.linalg.norm(off_axis) < 0.03  # the centroid of the part lies about 0.4 from the axis
    assert np.linalg.norm(stability.centre[:2] - offset[:2]) > 0.3


def test_a_slide_has_no_turn_axis() -> None:
    slide = Stability(0.001, np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0]), 100, None, np.zeros(3), 1.0)
    assert slide.turn_axis() is None
    screw = Stability(0.001, np.array([0.0, 0.0, 1.0, 0.0, 2.0, 0.0]) / np.sqrt(5.0), 100, None, np.zeros(3), 0.5)
    point, direction = screw.turn_axis()  # velocity w x (p - c) + s, s = (0, 1, 0) / sqrt 5: zero on x = -1
    np.testing.assert_allclose(direction, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(point, [-1.0, 0.0, 0.0], atol=1e-12)


def test_shared_sample_points_pin_the_turn_of_a_shape_of_revolution() -> None:
    """The same points on both sides (synthetic pairs): moving them along the surface leaves their partners."""
    points = spheroid(800, 0)
    shared = stability_of(points, points)
    independent = stability_of(points, spheroid(800, 1))
    assert shared.eigenvalue < WEAK_EIGENVALUE and shared.probe_ratio >= PINNED_RATIO and not shared.weak
    assert independent.probe_ratio < 1.2 and independent.weak
    assert weak_motion_warning(shared) is None


def test_a_caller_can_ask_for_a_firmer_pose() -> None:
    """``weak_below``: the same pose is weakly constrained below a higher floor, with the floor in the warning."""
    source, target = asymmetric_blob(800, 0), asymmetric_blob(800, 1)
    default = stability_of(source, target)
    firmer = pose_stability(source, target, KDTree(target), 0.1, weak_below=2 * default.eigenvalue)
    assert not default.weak and default.probe_ratio is None
    assert firmer.eigenvalue == default.eigenvalue and firmer.probe_ratio < PINNED_RATIO and firmer.weak
    assert f"< {2 * default.eigenvalue:g})" in weak_motion_warning(firmer)


def test_an_asymmetric_shape_pins_the_pose_down() -> None:
    stability = stability_of(asymmetric_blob(800, 0), asymmetric_blob(800, 1))
    assert stability is not None and stability.eigenvalue > 3 * WEAK_EIGENVALUE
    assert weak_motion_warning(stability) is None


def test_a_flat_overlap_can_slide() -> None:
    rng = np.random.default_rng(0)
    ridge = lambda p: np.c_[p, 0.2 * np.sin(3 * p[:, :1])]  # noqa: E731  # a surface that varies along x only
    source, target = ridge(rng.uniform(-1, 1, (800, 2))), ridge(rng.uniform(-1, 1, (800, 2)))
    stability = stability_of(source, target)
    assert stability is not None and stability.weak
    assert abs(stability.motion[4]) > 0.9  # sliding along y leaves every point on the surface
    assert weak_motion_warning(stability).startswith("weakly constrained: a slide along")


def test_the_figure_does_not_depend_on_units_position_or_orientation() -> None:
    source, target = asymmetric_blob(600, 2), asymmetric_blob(600, 3)
    R = Rotation.from_euler("zyx", [40, -20, 75], degrees=True).as_matrix()
    reference = stability_of(source, target)
    moved = stability_of(1000 * source @ R.T + 5e4, 1000 * target @ R.T + 5e4, max_distance=100.0)
    assert moved.eigenvalue == pytest.approx(reference.eigenvalue, rel=1e-6)
    assert moved.pairs == reference.pairs


def test_the_refinements_normals_give_the_same_figure() -> None:
    """With the target's normals at hand (``icp-plane``) nothing is computed again, and nothing changes."""
    source, target = spheroid(600, 2), spheroid(600, 3)
    surface = Surface.of(target)
    given = pose_stability(source, target, surface.tree, 0.1, surface)
    alone = stability_of(source, target)
    assert given.eigenvalue == pytest.approx(alone.eigenvalue, rel=1e-12) and given.pairs == alone.pairs
    assert given.probe_ratio == pytest.approx(alone.probe_ratio, rel=1e-12)


def test_too_few_pairs_give_no_figure_and_no_warning() -> None:
    target = asymmetric_blob(600, 3)
    assert stability_of(asymmetric_blob(600, 2) + 10.0, target) is None
    assert weak_motion_warning(None) is None


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return Registrar(BUNDLED, threads=2)


def test_a_registered_shape_of_revolution_is_not_reliable(registrar) -> None:
    """Two samples of a spheroid fit at any turn about its axis: the returned pose is a guess along it."""
    R = Rotation.from_euler("zyx", [20, 10, -15], degrees=True).as_matrix()
    result = registrar.register(spheroid(1024, 0), spheroid(1024, 1) @ R.T + [0.1, 0.2, -0.1], refine="icp-plane")
    assert result.inlier_ratio > 0.8  # it fits: only the free turn makes it unreliable
    assert result.stability < WEAK_EIGENVALUE and not result.reliable
    assert any(w.startswith("weakly constrained: a turn about the axis") for w in result.warnings)


def test_a_registered_asymmetric_shape_stays_reliable(registrar) -> None:
    R = Rotation.from_euler("zyx", [20, 10, -15], degrees=True).as_matrix()
    result = registrar.register(asymmetric_blob(1024, 0), asymmetric_blob(1024, 1) @ R.T + [0.1, 0.2, -0.1],
                                refine="icp-plane")
    assert result.stability > WEAK_EIGENVALUE and result.reliable
    assert not any(w.startswith("weakly constrained") for w in result.warnings)


def test_the_probe_of_paired_points_that_coincide_is_one_and_finite() -> None:
    """A stack of paired points at the turn's centre does not move along it: nothing pins the motion (ratio 1), and
    the step along it is not sized by a displacement of zero (an overflow)."""
    from service.stability import _probe_ratio

    rng = np.random.default_rng(3)
    tgt = rng.normal(size=(200, 3))
    centre = np.array([0.1, -0.2, 0.3])
    p = np.repeat(centre[None], 40, axis=0)  # [40, 3] coinciding paired points
    turn_only = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])  # [6] a pure turn about the points' centre
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ratio = _probe_ratio(p, np.full(40, 0.01), tgt, KDTree(tgt), centre, 1.0, turn_only)
    assert ratio == 1.0


def test_a_pipe_is_warned_of_its_slide_along_and_its_turn_about_its_axis() -> None:
    """Two samples of an open pipe: both the slide along its axis and the turn about it leave the fit; the warning
    named only the least constrained one."""
    def pipe(n: int, seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        z, a = rng.uniform(0.0, 4.0, n), rng.uniform(0.0, 2 * np.pi, n)
        return np.c_[0.5 * np.cos(a), 0.5 * np.sin(a), z]

    stability = stability_of(pipe(3000, 1), pipe(3000, 2))
    assert stability is not None and stability.weak and stability.next_eigenvalue < stability.weak_below
    warning = weak_motion_warning(stability)
    assert ("a slide along (" in warning and "a turn about the axis (" in warning), warning
    assert warning.endswith("hardly changes it either"), warning
    blob = stability_of(asymmetric_blob(2000, 1), asymmetric_blob(2000, 1))
    assert blob is not None and blob.next_eigenvalue >= blob.weak_below  # pinned every way: nothing to add
    # the bar a caller lowers (assess: 0.02 -> 0.01 for a free turn) is the one the second motion is held to
    lowered = dataclasses.replace(stability, weak_below=stability.next_eigenvalue * 0.5,
                                  eigenvalue=stability.next_eigenvalue * 0.1)
    assert "either" not in weak_motion_warning(lowered)
