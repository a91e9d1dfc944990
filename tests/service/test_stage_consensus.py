"""Stage consensus: a doubtful result against the pose the clouds' descriptors agree on, and rooms they confirm
(decisions/0085, 0086, 0087, 0089, 0090, 0091, 0092, 0093)."""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib

import numpy as np
import pytest
from pair_checks import needs_modelnet
from real_scan_cases import GENERAL, THINNED_TURNTABLE, real_case, skip_without, skip_without_general
from scipy.spatial.transform import Rotation
from shapes import room_scene

from bench.real_scans import Case, case_thresholds, data_dir, pair_cases, pose_errors, thresholds, turned
from bench.room_crops import cases
from bench.turntable_scans import Shape, analytic_shape, modelnet_shapes, turntable_pairs
from service.feature_match import FeaturePose, feature_pose
from service.options import RegistrationOptions
from service.quality import WORKING_LOOSE_FIT
from service.registrar import Registrar
from service.result import RegistrationResult
from service.stability import WEAK_SLIDE, WEAK_TURN
from service.stages.consensus import (
    CONFIRMED_BY_DESCRIPTORS,
    CONFIRMING_SUPPORT,
    CONSENSUS_SHARE,
    CONSENSUS_SUPPORT,
    DESCRIPTOR_CONSENSUS,
    ONE_PLACE_RIVAL,
    ONE_PLACE_SHARE,
    PARTIAL_OVERLAY,
    RELIABLE_CONSENSUS_SHARE,
    STRONG_SUPPORT,
    UNIQUE_SHARE,
    confirmed,
    confirmed_note,
    consensus,
    consensus_note,
    one_strong_place,
    settled_by_descriptors,
    share_to_keep,
)
from service.stages.normalise import Working
from service.stages.pipeline import Stages


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return general()


@functools.cache
def general(stage: bool = True) -> Registrar:
    """``general`` with the consensus stage or without it, loaded once per test process (a registrar keeps nothing
    between calls)."""
    skip_without_general()
    stages = Stages() if stage else dataclasses.replace(Stages(), consensus=lambda *a: a[2])
    return Registrar(GENERAL, threads=1, stages=stages)


def room_crop(label: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]:
    """``bench.room_crops``' case ``label`` (``seed``, 3 turns): source, target, src_to_tgt and its thresholds."""
    fragment, overlap = label.split("/o")[0], int(label.split("/o")[1][:2]) / 100
    skip_without(fragment.split("/")[0])
    crops = fragment_crops(fragment, overlap, seed)
    if label not in crops:
        raise AssertionError(f"no case {label}")
    sensor, *clouds = crops[label]
    source, target, truth = (c.copy() for c in clouds)  # the cache's arrays stay as made
    return source, target, truth, thresholds(sensor)


@functools.cache
def fragment_crops(fragment: str, overlap: float, seed: int) -> dict[str, tuple]:
    """``label: (sensor, source, target, src_to_tgt)`` of one fragment's cases, made once per test process."""
    return {name: (sensor, *clouds) for name, sensor, *clouds in cases(data_dir(), overlap, seed, 3, [fragment])}


def without_consensus() -> Registrar:
    return general(stage=False)


def clouds_key(*clouds: np.ndarray) -> tuple:
    """What tells clouds from others in the caches below: their shapes and a digest of their values."""
    return tuple((c.shape, c.dtype.str, hashlib.blake2b(np.ascontiguousarray(c).tobytes()).digest()) for c in clouds)


# Several tests read one case's registration and working clouds: each is made once per test process.
REGISTERED: dict[tuple, RegistrationResult] = {}
WORKING: dict[tuple, Working] = {}


def working(registrar: Registrar, source: np.ndarray, target: np.ndarray) -> Working:
    """The working clouds ``registrar`` makes of the pair, shared by the tests that ask (frozen; the stages only read
    them, as in one registration)."""
    key = (registrar, *clouds_key(source, target))
    if key not in WORKING:
        work = registrar.stages.normalise(registrar.stages.sample(registrar.stages.validate(
            source, target, None, {"refine": "icp-plane"}, 3, 128)), registrar.reference_radius)
        for value in vars(work).values():  # shared: a test that wrote into its arrays would change the others'
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
        WORKING[key] = work
    return WORKING[key]


def supported(work: Working, support: int) -> FeaturePose:
    """``work``'s feature pose as if ``support`` matched pairs agreed with it."""
    return dataclasses.replace(work.feature_pose, support=support)


def registered(registrar: Registrar, source: np.ndarray, target: np.ndarray, truth: np.ndarray,
               limits: tuple[float, float]) -> tuple[RegistrationResult, bool]:
    """The pair registered by ``registrar`` (a copy of its one registration per test process), and whether it is
    right."""
    key = (registrar, *clouds_key(source, target))
    if key not in REGISTERED:
        REGISTERED[key] = registrar.register(source, target, refine="icp-plane", rotation_search="auto")
    result = copy.deepcopy(REGISTERED[key])
    degrees, error = pose_errors(result.rotation, result.translation, truth)
    return result, bool(degrees < limits[0] and error < limits[1])


def test_the_feature_pose_counts_the_matched_pairs_that_agree_with_another_pose() -> None:
    rng = np.random.default_rng(0)
    cloud = room_scene(rng)
    moved = cloud @ Rotation.from_euler("z", 70, degrees=True).as_matrix().T + [0.5, -0.2, 0.1]
    pose = feature_pose(cloud, moved, voxel=0.1)
    assert pose is not None and pose.support >= CONSENSUS_SUPPORT
    # the pose refitted on the pairs that agreed with the best sample keeps about as many
    assert abs(pose.support_of(pose.rotation, pose.translation) - pose.support) <= 0.05 * pose.support
    half_turned = Rotation.from_euler("z", 180, degrees=True).as_matrix() @ pose.rotation
    assert pose.support_of(half_turned, pose.translation) < pose.support / 4


def test_a_room_crop_at_30_percent_overlap_registers_from_the_descriptors_consensus(registrar) -> None:
    """Cut from one 3DLoMatch fragment with a third of each window shared: the refinement lays more of the source on
    the target's walls half a turn off (172 deg) than at the truth; 54 matched patches agree with the truth, 5 with
    that pose. The pose refined from theirs lays 0.34 of the source on the target, a poor fit, and 52 pairs agree with
    it: the descriptors confirm it."""
    source, target, truth, limits = room_crop("3dlo_kitchen_34_21/source/o30/cut")
    result, right = registered(without_consensus(), source, target, truth, limits)
    assert not right and not result.reliable
    result, right = registered(registrar, source, target, truth, limits)
    assert right, pose_errors(result.rotation, result.translation, truth)
    assert "consensus" in result.timing_ms and result.reliable
    kinds = [w.split(":")[0] for w in result.warnings]
    assert kinds == ["poor fit", "descriptor consensus", CONFIRMED_BY_DESCRIPTORS], result.warnings
    assert result.warnings[1].startswith("descriptor consensus: 54 matched surface patches agree with this pose, 5")
    assert result.warnings[2].startswith(f"{CONFIRMED_BY_DESCRIPTORS}: 52 matched surface patches agree with this pose")
    assert len(result.source_index) == len(result.target_index) > 0 and result.source_index.max() < len(source)
    with_poses = registrar.register(source, target, refine="icp-plane", rotation_search="auto", return_iterations=True)
    assert len(with_poses.iteration_poses) == with_poses.iterations > 0  # the network's passes from the new pose


def test_a_right_result_that_the_descriptors_agree_with_is_kept(registrar) -> None:
    """At 70% overlap this crop's result is right and weakly constrained: the consensus looks and keeps it (and
    confirms it, below)."""
    source, target, truth, limits = room_crop("3dlo_homeat_41_38/source/o70/cut")
    result, right = registered(registrar, source, target, truth, limits)
    assert right and "consensus" in result.timing_ms
    assert not any(w.startswith("descriptor consensus") for w in result.warnings)


def test_a_reliable_room_result_half_a_turn_off_is_replaced(registrar) -> None:
    """At 30% overlap this crop's result passes every check 179 deg off, as a room turned onto its own walls; 18
    matched patches agree with the truth, 2 with that pose: under 0.3 of them, so the consensus replaces it."""
    source, target, truth, limits = room_crop("3dm_hotel3_15_8/source/o30/turned-3")
    result, right = registered(without_consensus(), source, target, truth, limits)
    assert not right and result.reliable
    result, right = registered(registrar, source, target, truth, limits)
    assert right, pose_errors(result.rotation, result.translation, truth)
    (note,) = (w for w in result.warnings if w.startswith("descriptor consensus"))
    assert note.startswith("descriptor consensus: 18 matched surface patches agree with this pose, 2 with")


def test_a_reliable_room_result_that_keeps_half_of_one_strong_place_gives_way_to_it(registrar) -> None:
    """A kitchen window at 70% overlap (seed 7) registers 4.4 deg and 0.28 m off (within the 0.3 m of the room
    thresholds, barely) and passes every check. The feature pose is 1.4 deg off: 118 matched pairs agree with it, no
    other place gets 0.3 of them, and the result keeps 0.66, more than the 0.3 a `reliable` room must keep. Of one
    strong place it must keep 0.8, so the pose replaces it: 0.18 deg and 8 mm off."""
    source, target, truth, limits = room_crop("3dlo_kitchen_34_21/source/o70/turned", seed=7)
    result, _ = registered(without_consensus(), source, target, truth, limits)
    assert result.reliable and pose_errors(result.rotation, result.translation, truth)[1] > 0.25
    pose = working(registrar, source, target).feature_pose
    assert pose.support == 118 and one_strong_place(pose)
    assert RELIABLE_CONSENSUS_SHARE * pose.support <= pose.support_of(result.rotation, result.translation) < (
        ONE_PLACE_SHARE * pose.support)
    result, _ = registered(registrar, source, target, truth, limits)
    degrees, metres = pose_errors(result.rotation, result.translation, truth)
    assert degrees < 1.0 and metres < 0.02, (degrees, metres)
    (note,) = (w for w in result.warnings if w.startswith(DESCRIPTOR_CONSENSUS))
    assert note.startswith(f"{DESCRIPTOR_CONSENSUS}: 118 matched surface patches agree with this pose, 78 with"), note


def test_only_a_reliable_room_must_keep_more_of_one_strong_place(registrar) -> None:
    """The kitchen window's result as registered without the stage keeps 78 of the strong pose's 118 pairs: `reliable`,
    the pose replaces it; not `reliable`, it keeps more than half of them, as any doubtful result must."""
    source, target, truth, limits = room_crop("3dlo_kitchen_34_21/source/o70/turned", seed=7)
    result, _ = registered(without_consensus(), source, target, truth, limits)
    work = working(registrar, source, target)
    options = RegistrationOptions(refine="icp-plane")
    replaced = consensus(registrar, work, result, options, 3, 128, {})
    assert any(w.startswith(DESCRIPTOR_CONSENSUS) for w in replaced.warnings), replaced.warnings
    doubtful = dataclasses.replace(result, reliable=False, warnings=["poor fit: inlier ratio 0.40 < 0.45"])
    kept = consensus(registrar, work, doubtful, options, 3, 128, {})
    assert not any(w.startswith(DESCRIPTOR_CONSENSUS) for w in kept.warnings), kept.warnings


def test_one_strong_place_needs_the_support_and_no_rival_near_it(registrar) -> None:
    """The kitchen window's feature pose is one strong place at 60 agreeing pairs, not at 59. The lumpy sphere's
    (scanned 24 deg apart) has 95, and another place has 60 of them: one place only from 201 pairs."""
    source, target, _, _ = room_crop("3dlo_kitchen_34_21/source/o70/turned", seed=7)
    kitchen = working(registrar, source, target).feature_pose
    assert 0 < kitchen.rival() < ONE_PLACE_RIVAL * STRONG_SUPPORT
    assert one_strong_place(dataclasses.replace(kitchen, support=STRONG_SUPPORT))
    assert not one_strong_place(dataclasses.replace(kitchen, support=STRONG_SUPPORT - 1))
    case = lumpy_sphere()
    sphere = working(registrar, case.source, case.target).feature_pose
    assert (sphere.support, sphere.rival()) == (95, 60) and not one_strong_place(sphere)
    assert not one_strong_place(dataclasses.replace(sphere, support=200))  # 60 = 0.3 * 200
    assert one_strong_place(dataclasses.replace(sphere, support=201))


def test_the_share_to_keep_by_result_clouds_and_refinement(registrar) -> None:
    source, target, truth, limits = room_crop("3dlo_kitchen_34_21/source/o30/cut")
    result, _ = registered(registrar, source, target, truth, limits)
    work = working(registrar, source, target)
    options = RegistrationOptions(refine="icp-plane")
    doubtful = dataclasses.replace(result, reliable=False)  # as it left the closing checks (the descriptors confirm it)
    assert share_to_keep(work, doubtful, options) == CONSENSUS_SHARE
    reliable = dataclasses.replace(result, reliable=True)
    assert share_to_keep(work, reliable, options) == RELIABLE_CONSENSUS_SHARE  # a room: the stricter share
    assert share_to_keep(work, doubtful, RegistrationOptions(refine="icp")) is None
    sparse = working(registrar, source[::10], target[::10])
    assert share_to_keep(sparse, doubtful, options) is None  # under 4 times the working points: nothing to describe


def test_a_reliable_room_that_overlays_all_its_source_is_not_looked_at(registrar) -> None:
    """Two thirds of a synthetic room onto the whole of it: a right pose lays all of the source on the target, and the
    pipeline's own checks settle such a room; only a result that overlays less than PARTIAL_OVERLAY of what a right
    pose reaches is looked at."""
    room = room_scene(np.random.default_rng(8))
    source, target = room[room[:, 0] < 2.7].astype(np.float32), room.astype(np.float32)
    turn = Rotation.from_euler("zx", [100, 20], degrees=True).as_matrix()
    source = source @ turn.T.astype(np.float32)
    result = registrar.register(source, target, refine="icp-plane", rotation_search="auto")
    truth = np.eye(4)
    truth[:3, :3] = turn.T  # src_to_tgt
    assert pose_errors(result.rotation, result.translation, truth)[0] < 1.0
    assert result.reliable and "consensus" not in result.timing_ms
    work = working(registrar, source, target)
    options = RegistrationOptions(refine="icp-plane")
    assert result.inlier_ratio >= PARTIAL_OVERLAY * work.surface_attainable_ratio
    assert share_to_keep(work, result, options) is None
    in_part = dataclasses.replace(result, inlier_ratio=0.8 * PARTIAL_OVERLAY * work.surface_attainable_ratio)
    assert share_to_keep(work, in_part, options) == RELIABLE_CONSENSUS_SHARE


def test_reliable_results_that_are_not_rooms_are_not_looked_at(registrar) -> None:
    case = real_case("dragon_96_72", 0, "scanned")
    result = registrar.register(case.source, case.target, refine="icp-plane", rotation_search="auto")
    assert result.reliable
    work = working(registrar, case.source, case.target)
    options = RegistrationOptions(refine="icp-plane")
    assert share_to_keep(work, result, options) is None
    assert share_to_keep(work, dataclasses.replace(result, reliable=False), options) == CONSENSUS_SHARE
    timing: dict[str, float] = {}
    assert consensus(registrar, work, result, options, 3, 128, timing) is result and not timing


def test_a_room_result_the_descriptors_agree_with_is_confirmed(registrar) -> None:
    """At 30% overlap this crop's result is right and lays 0.3-0.4 of the source on the target, a poor fit however
    right; the consensus keeps it, and 38 matched pairs agree with it (at least CONFIRMING_SUPPORT): `reliable`."""
    source, target, truth, limits = room_crop("3dlo_homeat_41_38/target/o30/turned-2")
    result, right = registered(without_consensus(), source, target, truth, limits)
    assert right and not result.reliable and [w.split(":")[0] for w in result.warnings] == ["poor fit"]
    result, right = registered(registrar, source, target, truth, limits)
    assert right and result.reliable
    assert [w.split(":")[0] for w in result.warnings] == ["poor fit", CONFIRMED_BY_DESCRIPTORS], result.warnings
    assert result.warnings[1].startswith(f"{CONFIRMED_BY_DESCRIPTORS}: 38 matched surface patches agree with this pose")


def test_a_room_result_too_few_pairs_agree_with_stays_doubtful(registrar) -> None:
    """The same crop at another turn: right, a poor fit, 25 matched pairs agree with it: not enough to confirm."""
    source, target, truth, limits = room_crop("3dlo_homeat_41_38/target/o30/turned-3")
    result, right = registered(registrar, source, target, truth, limits)
    assert right and "consensus" in result.timing_ms and not result.reliable
    assert [w.split(":")[0] for w in result.warnings] == ["poor fit"], result.warnings


def test_only_a_rooms_result_held_back_by_doubts_the_descriptors_settle_is_confirmed(registrar) -> None:
    """The rule's gates one by one on a right crop result with a poor fit: the support, another doubt, a result
    already `reliable`, clouds that are not rooms, and a pose off the target's surface."""
    source, target, truth, limits = room_crop("3dlo_homeat_41_38/target/o30/turned-3")
    result, _ = registered(registrar, source, target, truth, limits)
    room = working(registrar, source, target)
    made = confirmed(room, result, CONFIRMING_SUPPORT, room.feature_pose, replaced=False)
    assert made.reliable and made.warnings == [*result.warnings, made.warnings[-1]]
    assert made.warnings[-1].startswith(f"{CONFIRMED_BY_DESCRIPTORS}: {CONFIRMING_SUPPORT} matched surface patches")
    assert confirmed(room, result, CONFIRMING_SUPPORT - 1, room.feature_pose, replaced=False) is result
    low = dataclasses.replace(result, warnings=["low overlap: inlier ratio 0.21 < 0.3"])
    assert confirmed(room, low, 2 * CONFIRMING_SUPPORT, room.feature_pose, replaced=False) is low
    reliable = dataclasses.replace(result, reliable=True)  # its warnings kept: the flag alone stops the rule
    assert confirmed(room, reliable, 2 * CONFIRMING_SUPPORT, room.feature_pose, replaced=False) is reliable
    replaced = confirmed(room, result, CONFIRMING_SUPPORT, supported(room, 2 * CONFIRMING_SUPPORT), replaced=True)
    assert replaced.reliable  # a room's replaced result too, whatever share of the feature pose's support it keeps
    pose = room.feature_pose  # ... and whatever its rival: another place has 0.6 of this pose's support
    assert pose.rival() >= UNIQUE_SHARE * pose.support
    assert confirmed(room, result, CONFIRMING_SUPPORT, pose, replaced=True).reliable
    case = real_case("dragon_96_72", 0, "scanned")  # not a room: descriptors agreed on wrong poses there (row I)
    dragon = working(registrar, case.source, case.target)
    assert confirmed(dragon, result, 60, supported(dragon, 60), replaced=False) is result  # a poor fit: not a room
    slid = dataclasses.replace(result, translation=result.translation + 3 * room.inlier_distance)  # off the surface
    assert confirmed(room, slid, 2 * CONFIRMING_SUPPORT, room.feature_pose, replaced=False) is slid


@pytest.fixture(scope="module")
def poor_fit_crop(registrar) -> tuple[Working, RegistrationResult]:
    """A right room crop result that only a poor fit keeps from `reliable`, and its working clouds."""
    source, target, truth, limits = room_crop("3dlo_homeat_41_38/target/o30/turned-3")
    result, right = registered(registrar, source, target, truth, limits)
    assert right and not result.reliable
    return working(registrar, source, target), result


@pytest.mark.parametrize("doubts, settled", [
    (["poor fit: inlier ratio 0.30 < 0.45"], True),
    (["weakly constrained: a slide along (1.00, 0.00, 0.00) hardly changes the fit"], True),
    (["weakly constrained: a turn about the axis (0.00, 0.00, 1.00) hardly changes the fit"], True),
    (["ambiguous: a pose that moves the source 0.467 further fits almost as well (close fit 0.23 vs 0.26)"], True),
    (["poor fit: inlier ratio 0.30 < 0.45", "weakly constrained: a slide along (1.00, 0.00, 0.00)"], True),
    # a turn that fits as well: wrong quarter turns of rooms keep enough agreeing pairs (decisions/0089)
    (["ambiguous: a pose 90 deg away fits almost as well (close fit 0.72 vs 0.63)"], False),
    (["ambiguous: a pose 85 deg away fits what is not wall or floor at least as closely"], False),
    (["poor fit: inlier ratio 0.30 < 0.45", "ambiguous: a pose 178 deg away fits almost as well"], False),
    (["low overlap: inlier ratio 0.21 < 0.3"], False),
    (["loose fit: of the source points within 3 inlier distances of the target only 0.57 lie within one"], False),
    (["found by the second, denser rotation search only (the first fitted poorly)"], False),
    ([], False),
])
def test_the_doubts_the_descriptors_settle(poor_fit_crop, doubts: list[str], settled: bool) -> None:
    """A poor fit, weak constraint and another place that fits: the fit cannot place the source, matched patches
    can; a turn that fits as well, a low overlap or a loose fit they do not settle."""
    room, result = poor_fit_crop
    doubtful = dataclasses.replace(result, reliable=False, warnings=[*doubts, consensus_note(40, 3)])
    assert settled_by_descriptors(doubtful) is settled
    support = 2 * CONFIRMING_SUPPORT
    assert confirmed(room, doubtful, support, room.feature_pose, replaced=False).reliable is settled


@pytest.mark.parametrize("label, doubt", [
    ("3dlo_homeat_41_38/source/o70/cut", "weakly constrained"),
    ("3dm_geot_kitchen_6_0/target/o70/turned-2", "ambiguous: a pose that moves the source"),
])
def test_a_right_room_result_the_fit_cannot_place_is_confirmed_by_the_descriptors(registrar, label, doubt) -> None:
    """Two room crops at 70% overlap, right: one slides along its walls with little change of fit, the other has
    another place 0.47 m away that fits almost as well. Without the consensus each keeps that one doubt; with it,
    70-131 matched pairs agree with the pose, which is `reliable`."""
    source, target, truth, limits = room_crop(label)
    result, right = registered(without_consensus(), source, target, truth, limits)
    assert right and not result.reliable
    assert len(result.warnings) == 1 and result.warnings[0].startswith(doubt), result.warnings
    result, right = registered(registrar, source, target, truth, limits)
    assert right and result.reliable, result.warnings
    assert result.warnings[0].startswith(doubt) and result.warnings[-1].startswith(CONFIRMED_BY_DESCRIPTORS)


def turntable_case(shape: Shape, angle: float, variant: str) -> Case:
    """``bench.turntable_scans``' case of ``shape`` scanned at 0 and ``angle`` deg (seed 0, 2 turns), thinned as before
    decision 0095 (the cases below were measured so)."""
    for case in pair_cases(turntable_pairs(shape, [angle], THINNED_TURNTABLE), 0, (1.0,), 2):
        if case.variant == variant:
            return case
    raise AssertionError(f"no case {variant}")


def lumpy_sphere() -> Case:
    """A lumpy sphere scanned 24 deg apart (``turntable_case``): a copy of the one made per test process (it takes
    seconds to make, and three tests read it)."""
    return copy.deepcopy(scanned_lumpy_sphere())


@functools.cache
def scanned_lumpy_sphere() -> Case:
    return turntable_case(analytic_shape("lumpy_sphere"), 24.0, "scanned")


def registered_case(registrar: Registrar, case: Case) -> tuple[RegistrationResult, bool]:
    return registered(registrar, case.source, case.target, case.src_to_tgt, case_thresholds(case))


def test_a_round_objects_turn_the_descriptors_pin_is_confirmed(registrar) -> None:
    """A lumpy sphere scanned 24 deg apart on a turntable, right: a turn about its axis hardly changes the fit
    (`weakly constrained`), but 89 matched pairs, 0.94 of the feature pose's, agree with the pose: `reliable`."""
    case = lumpy_sphere()
    result, right = registered_case(without_consensus(), case)
    assert right and not result.reliable and [w.split(":")[0] for w in result.warnings] == ["weakly constrained"]
    result, right = registered_case(registrar, case)
    assert right and result.reliable, result.warnings
    assert result.warnings[-1].startswith(f"{CONFIRMED_BY_DESCRIPTORS}: 89 matched surface patches"), result.warnings


@needs_modelnet
def test_a_round_object_turned_off_the_descriptors_pose_stays_doubtful(registrar) -> None:
    """A lamp (ModelNet40's second test lamp) scanned 24 deg apart, turned as row O turns it (its pair is the 31st of
    `bench.turntable_scans`' default run: the 31st rotation drawn from seed 0): registered 24 deg off about its axis,
    weakly constrained; 54 matched pairs agree with it, but only 0.67 of the feature pose's 81: not confirmed."""
    pair = turntable_pairs(modelnet_shapes(["lamp"], 2)[1], [24.0], THINNED_TURNTABLE)[0]
    rng = np.random.default_rng(0)
    rotation = [Rotation.random(random_state=rng) for _ in range(31)][-1].as_matrix()
    source, truth = turned(pair.source, pair.src_to_tgt, rotation)
    result, right = registered(registrar, source, pair.target, truth, thresholds(pair.sensor))
    assert not right and not result.reliable
    assert [w.split(":")[0] for w in result.warnings] == ["weakly constrained"], result.warnings
    pose = working(registrar, source, pair.target).feature_pose
    assert pose.support == 81 and pose.support_of(result.rotation, result.translation) == 54


@needs_modelnet
def test_a_round_objects_feature_pose_in_one_place_put_in_the_results_place_is_confirmed(registrar) -> None:
    """A cup (ModelNet40's second test cup) scanned 24 deg apart: the refinement turns it far off about its axis.
    46 matched pairs agree with the feature pose, 7 with that result, so the stage puts the pose in its place (right,
    a weak turn); 42 pairs agree with it refined, and no other place the descriptors point to gets more than 12:
    `reliable`."""
    case = turntable_case(modelnet_shapes(["cup"], 2)[1], 24.0, "scanned")
    result, right = registered_case(without_consensus(), case)
    assert not right and not result.reliable
    pose = working(registrar, case.source, case.target).feature_pose
    assert (pose.support, pose.rival()) == (46, 12)
    result, right = registered_case(registrar, case)
    assert right and result.reliable, result.warnings
    assert [w.split(":")[0] for w in result.warnings] == [
        "weakly constrained", DESCRIPTOR_CONSENSUS, CONFIRMED_BY_DESCRIPTORS], result.warnings
    assert result.warnings[1].startswith(f"{DESCRIPTOR_CONSENSUS}: 46 matched surface patches agree with this pose, 7 "
                                         "with"), result.warnings
    assert result.warnings[-1].startswith(f"{CONFIRMED_BY_DESCRIPTORS}: 42 matched surface patches"), result.warnings


@needs_modelnet
def test_an_objects_slide_the_descriptors_place_in_one_place_is_confirmed(registrar) -> None:
    """A cup (ModelNet40's first test cup) scanned 24 deg apart, turned by the first rotation seed 0 draws: right,
    but a slide hardly changes the fit. 57 matched pairs agree with it, of the feature pose's 58, and no other place
    the descriptors point to gets more than 14: kept and `reliable`. Its scans are not range images (their density
    hardly follows the incidence angle), so a loose fit of the working target would be settled too; the entered
    target's loose fit never is."""
    case = turntable_case(modelnet_shapes(["cup"], 2)[0], 24.0, "turned")
    result, right = registered_case(without_consensus(), case)
    assert right and not result.reliable and len(result.warnings) == 1, result.warnings
    assert result.warnings[0].startswith(WEAK_SLIDE), result.warnings
    cup = working(registrar, case.source, case.target)
    assert cup.range_views == (None, None)
    assert (cup.feature_pose.support, cup.feature_pose.rival()) == (58, 14)
    loose = dataclasses.replace(result, warnings=[f"{WORKING_LOOSE_FIT} 0.63 lie within one, < 0.7 of the 0.96"])
    assert confirmed(cup, loose, 57, cup.feature_pose, replaced=False).reliable
    entered = dataclasses.replace(result, warnings=[
        "loose fit: of the source points within 3 inlier distances of the target's points only 0.600 lie within one"])
    assert confirmed(cup, entered, 57, cup.feature_pose, replaced=False) is entered
    result, right = registered_case(registrar, case)
    assert right and result.reliable, result.warnings
    assert [w.split(":")[0] for w in result.warnings] == ["weakly constrained", CONFIRMED_BY_DESCRIPTORS]
    assert result.warnings[-1].startswith(f"{CONFIRMED_BY_DESCRIPTORS}: 57 matched surface patches"), result.warnings


def test_over_objects_a_weak_turn_and_in_one_place_a_slide_are_settled(registrar) -> None:
    """The object rule's gates on the lumpy sphere's result: the share of the feature pose's support (0.9 of it
    exactly passes), the count, for the feature pose put in the result's place or a weak slide no other place with 0.6
    of its support (its rival has 60 pairs), the doubt (a turn with a slide, a poor fit or another place is not
    settled over clouds that are not rooms, nor a loose fit of range images, which free space judges) and the
    target's surface."""
    case = lumpy_sphere()
    result, _ = registered_case(without_consensus(), case)
    assert result.warnings[0].startswith(WEAK_TURN), result.warnings
    sphere = working(registrar, case.source, case.target)
    assert confirmed(sphere, result, 60, supported(sphere, 60), replaced=False).reliable
    assert confirmed(sphere, result, 54, supported(sphere, 60), replaced=False).reliable  # 0.9 of the pose's support
    assert confirmed(sphere, result, 53, supported(sphere, 60), replaced=False) is result
    low = CONFIRMING_SUPPORT - 1
    assert confirmed(sphere, result, low, supported(sphere, low), replaced=False) is result
    assert sphere.feature_pose.rival() == 60
    assert confirmed(sphere, result, 101, supported(sphere, 101), replaced=True).reliable
    assert confirmed(sphere, result, 100, supported(sphere, 100), replaced=True) is result  # a rival of 0.6 of it
    assert confirmed(sphere, result, 100, supported(sphere, 100), replaced=False).reliable  # kept: no rival asked
    slide = dataclasses.replace(result, warnings=[f"{WEAK_SLIDE} (0.00, 0.00, 1.00) hardly changes the fit"])
    for replaced in (False, True):  # kept or replaced, in one place only
        assert confirmed(sphere, slide, 101, supported(sphere, 101), replaced).reliable
        assert confirmed(sphere, slide, 100, supported(sphere, 100), replaced) is slide
    off = dataclasses.replace(slide, translation=result.translation + 3 * sphere.inlier_distance)
    assert confirmed(sphere, off, 101, supported(sphere, 101), replaced=False) is off  # the entered target's test
    with_turn = dataclasses.replace(result, warnings=[*result.warnings, *slide.warnings])
    assert confirmed(sphere, with_turn, 100, supported(sphere, 100), replaced=False) is with_turn
    assert confirmed(sphere, with_turn, 101, supported(sphere, 101), replaced=False).reliable
    assert sphere.range_views != (None, None)  # its scans are range images: free space judges a loose fit
    for doubt in (f"{WORKING_LOOSE_FIT} 0.63 lie within one, < 0.7 of the 0.96",
                  "weakly constrained: a turn about (0.00, 0.00, 1.00) with a slide hardly changes the fit",
                  "poor fit: inlier ratio 0.30 < 0.45",
                  "ambiguous: a pose that moves the source 0.01 further fits almost as well"):
        doubtful = dataclasses.replace(result, warnings=[doubt])
        assert confirmed(sphere, doubtful, 60, supported(sphere, 60), replaced=False) is doubtful
        assert confirmed(sphere, doubtful, 101, supported(sphere, 101), replaced=True) is doubtful
        assert confirmed(sphere, doubtful, 101, supported(sphere, 101), replaced=False) is doubtful
    slid = dataclasses.replace(result, translation=result.translation + 3 * sphere.inlier_distance)  # off the surface
    assert confirmed(sphere, slid, 60, supported(sphere, 60), replaced=False) is slid
    assert confirmed(sphere, slid, 101, supported(sphere, 101), replaced=True) is slid


def test_a_result_the_descriptors_confirm_meets_free_space_and_the_symmetry_check_again() -> None:
    """Kept or replaced, a result the consensus stage returns anew is judged again by the closing checks: here the
    stage confirms the result it was given, and the symmetry check's second look takes `reliable` back."""
    skip_without_general()
    judged: list[RegistrationResult] = []

    def symmetry(work, result, options, timing):  # the second look finds a turn that fits as well
        judged.append(result)
        if result.warnings and result.warnings[-1].startswith(CONFIRMED_BY_DESCRIPTORS):
            return dataclasses.replace(result, reliable=False, warnings=[*result.warnings, "ambiguous: a turn"])
        return result

    def confirming(registrar, work, result, *args):
        return dataclasses.replace(result, reliable=True, warnings=[*result.warnings, confirmed_note(41)])

    stages = dataclasses.replace(Stages(), consensus=confirming, symmetry=symmetry)
    source, target, truth, limits = room_crop("3dlo_homeat_41_38/target/o30/turned-2")
    checking = Registrar(GENERAL, threads=1, stages=stages)
    judged.clear()  # the registrar's own first call, at start
    result, right = registered(checking, source, target, truth, limits)
    assert len(judged) == 2 and judged[1].reliable and judged[1].warnings[-1].startswith(CONFIRMED_BY_DESCRIPTORS)
    assert right and not result.reliable and result.warnings[-1] == "ambiguous: a turn"
