"""Stage guess: the caller's ``initial_transform`` as a candidate beside the network's pose, so that a network that
moves a good guess away cannot lose it."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from real_scan_cases import GENERAL, real_case, skip_without_general
from scipy.spatial.transform import Rotation
from shapes import lumpy_sphere, room_scene

from bench.real_scans import near_truth_starts, pose_errors, thresholds, turned
from service.registrar import Registrar
from service.rotation_search import SearchCandidate, rotation_between_deg
from service.stages.anchor import anchor
from service.stages.guess import KEPT_DEG, guess_candidate, keeps_guess
from service.stages.network import Candidates, network
from service.stages.normalise import normalise, to_caller
from service.stages.pipeline import Stages
from service.stages.sample import sample
from service.stages.search import search
from service.stages.validate import validate

AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
T_TRUE = np.array([0.4, 1.0, -2.0])


def pair_and_guess(degrees_off: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two samples of one surface, the source turned 70 deg, and a ``[4, 4]`` guess ``degrees_off`` from the truth:
    (source, target, R, guess)."""
    R = Rotation.from_rotvec(np.radians(70) * AXIS).as_matrix()
    source, target = (lumpy_sphere(6_000, seed=1) - T_TRUE) @ R, lumpy_sphere(6_000, seed=2)
    off = Rotation.from_rotvec(np.radians(degrees_off) * np.array([1.0, 0.0, 0.0])).as_matrix()
    guess = np.eye(4)
    guess[:3, :3], guess[:3, 3] = R @ off, T_TRUE
    return source, target, R, guess


def moved(found: Candidates, turn: np.ndarray = np.eye(3), shift: float = 0.0) -> Candidates:
    """``found`` with every candidate's pose turned by ``turn [3, 3]`` and moved by ``shift`` normalised units along
    each axis: a stage that moves the caller's guess away."""
    poses = [SearchCandidate(c.output, c.start, turn @ c.rotation, turn @ c.translation + shift) for c in found.poses]
    return Candidates(poses, found.net_s, found.net_t)


def turning_network(registrar, work, *args) -> Candidates:
    """The plain network stage with its pose turned 90 deg."""
    return moved(network(registrar, work, *args), Rotation.from_rotvec(np.radians(90) * AXIS).as_matrix())


def turning_search(registrar, work, *args, **kwargs) -> Candidates:
    """The search stage with every candidate's pose turned 120 deg about y."""
    turn = Rotation.from_rotvec(np.radians(120) * np.array([0.0, 1.0, 0.0])).as_matrix()
    return moved(search(registrar, work, *args, **kwargs), turn)


def displacing_network(registrar, work, *args) -> Candidates:
    """The plain network stage with its pose moved two normalised units along each axis: it overlays nothing."""
    return moved(network(registrar, work, *args), shift=2.0)


@pytest.fixture(scope="module")
def general() -> Registrar:
    skip_without_general()
    return Registrar(GENERAL, threads=1)


def test_the_added_candidate_is_the_callers_guess() -> None:
    source, target, _, guess = pair_and_guess(5)
    request, _ = anchor(validate(source, target, None, {"initial_transform": guess}, 4, 128))
    work = normalise(sample(request), 1.0)
    plain = SearchCandidate(None, np.eye(3), Rotation.from_rotvec([0.0, 0.2, 0.0]).as_matrix(), np.ones(3))
    found = guess_candidate(work, Candidates([plain], work.idx_s, work.idx_t))
    assert len(found.poses) == 2 and found.poses[0] is plain and found.feature_support == 0
    R, t = to_caller(work, found.poses[1].rotation, found.poses[1].translation)
    np.testing.assert_allclose(R, request.R_init, atol=1e-9)
    np.testing.assert_allclose(t, request.t_init, atol=1e-9)


@pytest.mark.parametrize("rotation_search", [False, "auto"])
def test_a_guess_the_network_moves_away_is_kept(general, rotation_search) -> None:
    source, target, R, guess = pair_and_guess(5)
    turned = Registrar(GENERAL, threads=1, stages=dataclasses.replace(Stages(), network=turning_network))
    result = turned.register(source, target, refine="icp-plane", rotation_search=rotation_search,
                             initial_transform=guess)
    assert rotation_between_deg(result.rotation, R) < 1.0 and np.linalg.norm(result.translation - T_TRUE) < 0.02


def test_a_guess_that_overlays_well_asks_for_no_feature_candidate(general) -> None:
    """The plain pass's overlay is its best candidate's: a right guess beside a network pose turned away is enough."""
    source, target, R, guess = pair_and_guess(5)
    displaced = Registrar(GENERAL, threads=1, stages=dataclasses.replace(Stages(), network=displacing_network))
    result = displaced.register(source, target, refine="icp-plane", rotation_search="auto", initial_transform=guess)
    assert rotation_between_deg(result.rotation, R) < 1.0
    assert "features" not in result.timing_ms and "search" not in result.timing_ms


@pytest.mark.parametrize("guess_stage", [guess_candidate, lambda work, found: found])
def test_the_search_keeps_a_guess_among_its_candidates(general, guess_stage) -> None:
    source, target, R, guess = pair_and_guess(5)
    stages = dataclasses.replace(Stages(), search=turning_search, guess=guess_stage)
    result = Registrar(GENERAL, threads=1, stages=stages).register(
        source, target, refine="icp-plane", rotation_search=True, initial_transform=guess)
    kept = rotation_between_deg(result.rotation, R) < 1.0
    assert kept == (guess_stage is guess_candidate)


def test_without_the_stage_the_network_moves_the_guess_away(general) -> None:
    source, target, R, guess = pair_and_guess(5)
    stages = dataclasses.replace(Stages(), network=turning_network, guess=lambda work, found: found)
    result = Registrar(GENERAL, threads=1, stages=stages).register(
        source, target, refine="icp-plane", rotation_search=False, initial_transform=guess)
    assert rotation_between_deg(result.rotation, R) > 45


def test_only_a_request_with_a_guess_adds_the_candidate(general) -> None:
    calls = []

    def counted(work, found):
        calls.append(len(found.poses))
        return guess_candidate(work, found)

    registrar = Registrar(GENERAL, threads=1, stages=dataclasses.replace(Stages(), guess=counted), warmup=False)
    source, target, R, guess = pair_and_guess(5)
    registrar.register(source, target, refine="icp-plane")
    assert calls == []
    result = registrar.register(source, target, refine="icp-plane", initial_transform=guess)
    assert calls == [1] and rotation_between_deg(result.rotation, R) < 1.0


def test_a_real_range_image_keeps_a_guess_the_network_turns_away() -> None:
    """``dragon_96_48`` as scanned, started 10 deg from the truth: the network alone turns it about 25 deg away."""
    case = real_case("dragon_96_48", 0, "scanned")
    start = near_truth_starts([case], 10.0, 0)[0]
    result = Registrar(GENERAL).register(case.source, case.target, refine="icp-plane", initial_transform=start)
    degrees, error = pose_errors(result.rotation, result.translation, case.src_to_tgt)
    max_degrees, max_error = thresholds(case.sensor)
    assert degrees < max_degrees and error < max_error, (degrees, error)


def room_and_guess(degrees_off: float, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two thirds of a synthetic room turned by a seeded rotation (the source), the room (the target), the truth
    ``[4, 4]``, and a guess: the truth after the source is turned ``degrees_off`` about ``axis`` at its centroid."""
    room = room_scene(np.random.default_rng(0)).astype(np.float32)
    source, truth = turned(room[room[:, 0] < 2.7], np.eye(4), Rotation.random(random_state=5).as_matrix())
    off = np.eye(4)
    off[:3, :3] = Rotation.from_rotvec(np.radians(degrees_off) * axis).as_matrix()
    centre = source.mean(0, dtype=np.float64)
    off[:3, 3] = centre - off[:3, :3] @ centre
    return source, room, truth, truth @ off


def test_a_room_that_keeps_the_callers_guess_is_not_searched_for_being_a_room(general) -> None:
    source, target, truth, guess = room_and_guess(5, np.array([0.0, 0.0, 1.0]))
    result = general.register(source, target, refine="icp-plane", rotation_search="auto", initial_transform=guess)
    degrees, error = pose_errors(result.rotation, result.translation, truth)
    assert degrees < 1.0 and error < 0.02, (degrees, error)
    assert "search" not in result.timing_ms
    unguided = general.register(source, target, refine="icp-plane", rotation_search="auto")
    assert "search" in unguided.timing_ms  # a room is searched for being one (docs/decisions/0023)


def test_a_room_guessed_a_quarter_turn_off_is_still_registered(general) -> None:
    source, target, truth, guess = room_and_guess(90, np.array([0.0, 0.0, 1.0]))
    result = general.register(source, target, refine="icp-plane", rotation_search="auto", initial_transform=guess)
    degrees, error = pose_errors(result.rotation, result.translation, truth)
    assert degrees < 1.0 and error < 0.02, (degrees, error)


def test_a_result_keeps_the_guess_within_kept_deg_of_it() -> None:
    source, target, _, guess = pair_and_guess(0)
    request, _ = anchor(validate(source, target, None, {"initial_transform": guess}, 4, 128))
    work = normalise(sample(request), 1.0)

    def result_at(degrees: float) -> SimpleNamespace:  # keeps_guess reads the result's rotation only
        return SimpleNamespace(rotation=Rotation.from_rotvec(np.radians(degrees) * AXIS).as_matrix() @ request.R_init)

    for degrees, kept in ((KEPT_DEG - 1, True), (KEPT_DEG + 1, False), (90, False)):
        assert keeps_guess(work, result_at(degrees)) is kept
