"""The assess stage's check on a dense target's surface: a pose that leaves the source near but off the surface is
not reliable."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from real_scan_cases import THINNED_TURNTABLE
from scipy.spatial.transform import Rotation
from shapes import room_scene
from stage_inputs import working_clouds

from bench.real_scans import load_cases, pose_errors, thresholds
from bench.turntable_scans import analytic_shape, turntable_pairs
from service.quality import WORKING_LOOSE_FIT
from service.registrar import Registrar
from service.stability import WEAK_EIGENVALUE, Stability, weak_motion_warning
from service.stages.assess import RELIABLE_STABILITY_ON_SURFACE, off_the_surface, turns_at_the_common_floor

GENERAL = Path(__file__).resolve().parents[2] / "service" / "models" / "general"
R_TRUE = Rotation.from_euler("zyx", [20.0, 0.0, 0.0], degrees=True).as_matrix()
T_TRUE = np.array([0.6, -0.3, 0.1])


def real_data_dir() -> Path:
    return Path(os.environ.get("MFGNET_REAL_DATA") or Path(__file__).resolve().parents[3] / "shared" / "data" / "real")


def room(target_points: int | None = None):
    """Two overlapping partial views of one furnished room (metres) as a registration's working clouds."""
    scene = room_scene(np.random.default_rng(3), 2000, boxes=30)
    source, target = scene[scene[:, 0] < 3.0], scene[scene[:, 0] > 1.0] @ R_TRUE.T + T_TRUE
    if target_points is not None:
        target = target[np.random.default_rng(0).choice(len(target), target_points, replace=False)]
    return working_clouds(source, target, reference_radius=1.0)[0]


def turned_about_the_target(work, degrees: float) -> tuple[np.ndarray, np.ndarray]:
    """The true pose followed by a turn of ``degrees`` about the vertical through the target's centroid."""
    turn = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    centre = work.tgt_e.mean(axis=0)
    return turn @ R_TRUE, turn @ T_TRUE + centre - turn @ centre


def test_the_right_pose_lies_on_the_surface_and_a_turned_one_does_not():
    work = room()
    assert off_the_surface(work, R_TRUE, T_TRUE) is None
    assert off_the_surface(work, *turned_about_the_target(work, 2.0)) is None
    warning = off_the_surface(work, *turned_about_the_target(work, 20.0))
    assert warning is not None and warning.startswith("loose fit: of the source points within 3 inlier distances of")
    assert not warning.startswith(WORKING_LOOSE_FIT)  # the entered target's: never settled by descriptors (0093)


def test_a_target_no_denser_than_its_working_cloud_is_not_checked():
    work = room(target_points=1500)  # under 4 x 768 points: the working cloud's own tight-fit test decides
    assert off_the_surface(work, *turned_about_the_target(work, 20.0)) is None


def test_a_room_registered_wrong_is_not_called_reliable():
    """A turned 3DMatch hotel fragment (the second turn of `bench.real_scans --seed 1 --turns 4`) comes back 44 deg
    off in metres and 179 deg off in millimetres; its fit on the working clouds passed every other test."""
    if not (real_data_dir() / "3dm_hotel3_15_8.npz").exists():
        pytest.skip(f"real-scan set absent ({real_data_dir()}; set MFGNET_REAL_DATA)")
    registrar = Registrar(GENERAL)
    cases = [
        c
        for c in load_cases(real_data_dir(), 1, (1.0, 1000.0), turns=4)
        if c.name == "3dm_hotel3_15_8" and c.variant == "turned-2"
    ]
    assert len(cases) == 2
    for case in cases:
        result = registrar.register(case.source, case.target, refine="icp-plane", rotation_search="auto")
        degrees, distance = pose_errors(result.rotation, result.translation, case.src_to_tgt)
        max_degrees, max_distance = thresholds(case.sensor, case.scale)
        assert not result.reliable or (degrees < max_degrees and distance < max_distance), (case.scale, degrees)


def test_the_reliable_rule_judges_a_sparse_target_by_its_density_and_a_dense_one_by_its_surface():
    """The surface estimate and its factors (0.45, 0.70) only where the entered target samples the surface densely;
    elsewhere the density estimate with its own (0.5, 0.72) (docs/decisions/0026)."""
    from service.stages.assess import reliable_attainable

    sparse = room(target_points=1500)
    assert reliable_attainable(sparse) == (sparse.attainable_ratio, False)  # the density estimate and its factors
    dense = room()
    assert reliable_attainable(dense) == (dense.surface_attainable_ratio, True)


@pytest.mark.parametrize("dense", [True, False])
def test_poor_fit_is_the_reliable_rules_band_below_its_share_of_the_attainable_ratio(dense: bool):
    """A real range-image pair (dense: the surface estimate) and a synthetic room target of 1,500 points (the density
    estimate): poor fit from the fixed 0.3 up to the rule's share of what a right pose reaches."""
    from real_scan_cases import real_case

    from service.quality import RELIABLE_RELATIVE_RATIO, RELIABLE_RELATIVE_RATIO_ON_SURFACE
    from service.stages.assess import poor_fit, reliable_attainable

    if dense:
        case = real_case("dragon_48_24", 0, "scanned")
        work, _ = working_clouds(case.source, case.target)
        attainable, on_surface = reliable_attainable(work)
        assert on_surface
        reach = RELIABLE_RELATIVE_RATIO_ON_SURFACE * attainable
        assert reach > 0.4  # the surface estimate of a range image is about 1
    else:
        work = room(target_points=1500)
        reach = RELIABLE_RELATIVE_RATIO * work.attainable_ratio
    for ratio in np.linspace(0.0, 1.0, 101):
        assert poor_fit(work, float(ratio)) is bool(0.3 <= ratio < reach), ratio


@pytest.mark.parametrize(
    ("motion", "eigenvalue", "weak"),
    [
        ((1.0, 0.0, 0.0, 0.0, 0.0, 0.0), 0.015, False),  # a turn: the common floor (the symmetry check turns it)
        ((0.0, 0.0, 0.0, 1.0, 0.0, 0.0), 0.015, True),  # a slide: the dense target's firmer floor
        ((1.0, 0.0, 0.0, 0.0, 0.0, 0.0), 0.008, True),  # a turn below the common floor
    ],
)
def test_on_a_dense_target_a_free_turn_is_judged_at_the_common_floor_and_a_slide_at_the_firmer_one(
    motion, eigenvalue, weak
):
    dense = Stability(eigenvalue, np.array(motion), 500, probe_ratio=1.0, weak_below=RELIABLE_STABILITY_ON_SURFACE)
    judged = turns_at_the_common_floor(dense)
    assert judged.weak is weak
    assert (weak_motion_warning(judged) is not None) is weak
    sparse = Stability(eigenvalue, np.array(motion), 500, probe_ratio=1.0)  # the common floor already: as it is
    assert turns_at_the_common_floor(sparse) is sparse and turns_at_the_common_floor(None) is None


def test_a_turntable_scan_of_a_smooth_blob_is_reliable_though_it_turns_below_the_dense_floor():
    """The asymmetric blob scanned 24 deg apart on a turntable (`bench.turntable_scans`, `asymmetric_blob_24_0` as
    scanned, thinned as before decision 0095): registered right, its least constrained motion a turn at 0.018, between
    the common floor and a dense target's; the symmetry check turns it about that axis and finds nothing that fits as
    well, so it is `reliable` (before, `weakly constrained: ... < 0.02`)."""
    pair = turntable_pairs(analytic_shape("asymmetric_blob"), [24.0], THINNED_TURNTABLE)[0]
    result = Registrar(GENERAL).register(pair.source, pair.target, refine="icp-plane", rotation_search="auto")
    degrees, distance = pose_errors(result.rotation, result.translation, pair.src_to_tgt)
    assert degrees < 1.0 and distance < 0.001, (degrees, distance)
    assert WEAK_EIGENVALUE < result.stability < RELIABLE_STABILITY_ON_SURFACE, result.stability
    assert result.reliable, result.warnings


def test_the_reverse_fit_is_offered_on_dense_targets_that_are_not_rooms():
    """Sparse targets and rooms keep the source-side ratio alone (decisions/0084): there a wrong pose explains a cut
    target as well as a right one."""
    from real_scan_cases import real_case

    from service.quality import reverse_fit
    from service.stages.assess import reverse_fit_on
    from service.stages.ranking import plane_frames_on_the_surface

    dense_room = room()
    assert plane_frames_on_the_surface(dense_room) and reverse_fit_on(dense_room, R_TRUE, T_TRUE) is None
    assert reverse_fit_on(room(target_points=1500), R_TRUE, T_TRUE) is None  # a sparse target
    case = real_case("dragon_48_24", 0, "scanned")
    work, _ = working_clouds(case.source, case.target)
    R, t = case.src_to_tgt[:3, :3], case.src_to_tgt[:3, 3]
    offered = reverse_fit_on(work, R, t)
    assert "source_attainable_ratio" not in vars(work)  # measured only where quality.assess asks
    fit = offered()
    assert fit == reverse_fit(work.working_source, work.tgt_w, R, t, work.inlier_distance,
                              work.source_attainable_ratio)
    assert fit.attainable > 0.9 and fit.ratio > 0.5  # the source's surface estimate; the scans overlap by most


def test_a_wrong_pose_between_scattered_clouds_is_not_reliable():
    """A volume of random points (the README's former example cloud, density falling along y and z) turned 150 deg
    about z: the default request comes back 92 deg off with 0.38 of the source within an inlier distance of the
    target, which a right pose of two independent samples would not beat, as the clouds' 768 working points lie
    farther apart than that distance; it was `reliable` with no warning. The same clouds 30 deg apart share their
    points: the right pose lays every point on one of the target's and stays `reliable`."""
    registrar = Registrar(GENERAL)
    source = np.random.default_rng(0).uniform(size=(2000, 3)) ** [1, 2, 3]  # [N, 3]
    for degrees, right in ((150.0, False), (30.0, True)):
        rotation = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
        result = registrar.register(source, source @ rotation.T + [0.1, 0.0, 0.0], refine="icp-plane",
                                    rotation_search="auto")
        error = np.degrees(np.arccos(np.clip((np.trace(result.rotation.T @ rotation) - 1) / 2, -1, 1)))
        assert bool(error < 1.0) is right and result.reliable is right, (degrees, error, result.warnings)
        assert any(w.startswith("scattered points") for w in result.warnings) is not right
