"""Rotation search: initial rotations covering SO(3), batched network loop, hypothesis selection, results."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob, ellipsoid_surface

from service.manifest import bundled_models_dir
from service.registrar import InputError, Registrar, needs_search
from service.result import RegistrationResult
from service.rotation_search import (
    SEARCH_KEYPOINTS,
    SEARCH_POINTS,
    SearchCandidate,
    ambiguity_warning,
    distinct_candidates,
    search_rotations_for,
)

BUNDLED = bundled_models_dir() / "clean"
needs_model = pytest.mark.skipif(not (BUNDLED / "manifest.json").exists(), reason="bundled model 'clean' absent")


def angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Rotation angle of ``R_a^T R_b`` in degrees."""
    return float(np.degrees(Rotation.from_matrix(R_a.T @ R_b).magnitude()))


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    if not (BUNDLED / "manifest.json").exists():
        pytest.skip("bundled model 'clean' absent")
    return Registrar(BUNDLED, threads=2)


@pytest.fixture(scope="module")
def blob_150(registrar) -> Callable[..., RegistrationResult]:
    """``blob_pair(150.0)`` registered by ``registrar`` with the options given, each once per module: the recovery,
    ``auto`` and symmetry tests ask for the same registrations (unpatched), and each gets a copy."""
    source, target, _, _ = blob_pair(150.0)
    results: dict[tuple, RegistrationResult] = {}

    def register(**options) -> RegistrationResult:
        key = tuple(sorted(options.items()))
        if key not in results:
            results[key] = registrar.register(source, target, **options)
        return copy.deepcopy(results[key])

    return register


# --- the initial rotations ------------------------------------------------------------------------


@pytest.mark.parametrize(("count", "covering_deg"), [(24, 62.8), (60, 44.5)])
def test_search_rotations_are_a_finite_rotation_group_covering_so3(count: int, covering_deg: float) -> None:
    H = search_rotations_for(count)
    assert H.shape == (count, 3, 3)
    np.testing.assert_allclose(H @ H.transpose(0, 2, 1), np.broadcast_to(np.eye(3), H.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(H), 1.0, atol=1e-12)
    assert any(np.allclose(h, np.eye(3)) for h in H)
    products = (H[:, None] @ H[None]).reshape(-1, 9)  # closed under composition: a group
    assert all(np.abs(H.reshape(-1, 9) - p).max(axis=1).min() < 1e-9 for p in products)
    samples = Rotation.random(20_000, random_state=0).as_matrix()  # every rotation is near one of them
    cos = (np.einsum("hij,sij->sh", H, samples) - 1) / 2  # [S, H] cosine of the angle between them
    nearest = np.degrees(np.arccos(np.clip(cos, -1, 1))).min(axis=1)  # [S]
    assert nearest.max() <= covering_deg
    np.testing.assert_array_equal(search_rotations_for(count), H)  # deterministic (and cached)


def test_unsupported_search_size_is_an_input_error() -> None:
    with pytest.raises(InputError, match="search_rotations"):
        search_rotations_for(12)


# --- the batched network loop ---------------------------------------------------------------------


def rotated_copies(count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` copies of one cloud under the first search rotations ``[count, 256, 3]`` and a target ``[256, 3]``."""
    cloud = asymmetric_blob(256, 1).astype(np.float32)
    batch = (cloud @ search_rotations_for(24)[:count].transpose(0, 2, 1)).astype(np.float32)
    return batch, asymmetric_blob(256, 2).astype(np.float32)


@needs_model
def test_batched_run_network_matches_one_pair_at_a_time(registrar) -> None:
    batch, target = rotated_copies(3)  # [3, 256, 3], [256, 3]
    timing: dict[str, float] = {}
    outputs = registrar.run_network(batch, target, 2, 64, timing)
    assert len(outputs) == 3 and {"encoder", "iterations", "svd"} <= set(timing)
    for source, out in zip(batch, outputs, strict=True):
        one = registrar.run_network(source, target, 2, 64)
        np.testing.assert_array_equal(out.src_kp, one.src_kp)
        np.testing.assert_array_equal(out.tgt_kp, one.tgt_kp)
        np.testing.assert_array_equal(out.matched, one.matched)
        np.testing.assert_allclose(out.rotation, one.rotation, atol=1e-5)
        np.testing.assert_allclose(out.translation, one.translation, atol=1e-5)
    different = registrar.run_network(batch[:2], target[:200], 1, 64)  # N != M: one encoder call per side
    assert len(different) == 2 and different[0].tgt_kp.max() < 200


@needs_model
def test_a_pruned_loop_ends_where_the_full_loop_takes_the_kept_rows(registrar) -> None:
    """Advancing some rows of a loop (select) and joined batches give each row's result of the whole loop."""
    from service.network_loop import NetworkLoop

    batch, target = rotated_copies(6)  # [6, 256, 3], [256, 3]
    timing: dict[str, float] = {}
    full = registrar.start_network(batch, target, 64, timing, same_source=True)
    full.advance(3, timing, batch=1)
    parts = [registrar.start_network(batch[r : r + 3], target, 64, timing, same_source=True) for r in (0, 3)]
    for part in parts:
        part.advance(1, timing, batch=1)
    kept = np.array([4, 1])
    pruned = NetworkLoop.join(parts).select(kept)
    pruned.advance(3, timing, batch=1)
    assert pruned.done == 3 and len(pruned.cumulative) == 3
    for got, want in zip(pruned.outputs(), [full.outputs()[k] for k in kept], strict=True):
        np.testing.assert_array_equal(got.src_kp, want.src_kp)
        np.testing.assert_array_equal(got.matched, want.matched)
        np.testing.assert_allclose(got.rotation, want.rotation, atol=1e-6)
        np.testing.assert_allclose(got.translation, want.translation, atol=1e-6)
        for (R_a, t_a), (R_b, t_b) in zip(got.cumulative, want.cumulative, strict=True):
            np.testing.assert_allclose(R_a, R_b, atol=1e-6)
            np.testing.assert_allclose(t_a, t_b, atol=1e-6)
    with pytest.raises(ValueError, match="different iterations"):
        NetworkLoop.join([pruned, parts[0]])


@needs_model
def test_rigid_copies_share_the_source_neighbour_graph(registrar, monkeypatch) -> None:
    batch, target = rotated_copies(4)  # [4, 256, 3], [256, 3]
    built: list[int] = []
    original = registrar.neighbours
    monkeypatch.setattr(registrar, "neighbours", lambda points: built.append(len(points)) or original(points))
    shared = registrar.run_network(batch, target, 2, 64, same_source=True)
    assert built == [1, 1]  # one graph for the four rotated sources, one for the target
    built.clear()
    separate = registrar.run_network(batch, target, 2, 64)
    assert built == [4, 1]
    for a, b in zip(shared, separate, strict=True):  # the k-NN graph is rotation invariant
        np.testing.assert_array_equal(a.src_kp, b.src_kp)
        np.testing.assert_array_equal(a.matched, b.matched)
        np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-6)


@needs_model
def test_a_precomputed_target_embedding_gives_the_same_result(registrar) -> None:
    batch, target = rotated_copies(3)  # [3, 256, 3], [256, 3]
    embedded = registrar.embed_cloud(target)
    reused = registrar.run_network(batch, target, 2, 64, target=embedded)
    fresh = registrar.run_network(batch, target, 2, 64)
    for a, b in zip(reused, fresh, strict=True):
        np.testing.assert_array_equal(a.tgt_kp, b.tgt_kp)
        np.testing.assert_array_equal(a.matched, b.matched)
        np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-5)
    with pytest.raises(ValueError, match="target embedding"):
        registrar.run_network(batch, target[:200], 2, 64, target=embedded)


def spy_on_embedded_sizes(registrar: Registrar, monkeypatch) -> list[tuple[int, int]]:
    """``(batch, points)`` of every encoder call of ``registrar``."""
    embedded: list[tuple[int, int]] = []
    original = registrar.embed
    monkeypatch.setattr(registrar, "embed", lambda pts, nb=None: embedded.append(pts.shape[:2]) or original(pts, nb))
    return embedded


@needs_model
def test_the_rotation_search_embeds_the_target_once(registrar, monkeypatch) -> None:
    sizes = spy_on_embedded_sizes(registrar, monkeypatch)
    source, target = asymmetric_blob(300, 1), asymmetric_blob(300, 2)
    registrar.register(source, target, rotation_search=True, refine="none")
    embedded = [batch for batch, _ in sizes]  # clouds per encoder call
    assert embedded[0] == 1 and sum(embedded) == 1 + 24  # the target, then the 24 rotated sources in chunks
    assert max(embedded[1:]) <= 4  # rotation_search.SEARCH_BATCH


# --- registration ---------------------------------------------------------------------------------


@needs_model
def test_rotation_search_recovers_a_150_degree_rotation_that_plain_registration_misses(blob_150) -> None:
    _, _, R, t = blob_pair(150.0)  # the target: 800 of the source's 1024 points, turned 150 deg and moved
    plain = blob_150(refine="icp")
    assert angle_deg(plain.rotation, R) > 30.0  # without the search: far off (the network knows <= 45 degrees)

    found = blob_150(refine="icp", rotation_search=True)
    assert angle_deg(found.rotation, R) < 2.0
    assert np.abs(found.translation - t).max() < 0.05
    assert found.reliable and found.inlier_ratio > 0.9
    assert {"search", "search_per_hypothesis", "encoder", "refine", "total"} <= set(found.timing_ms)
    assert found.timing_ms["search_per_hypothesis"] == pytest.approx(found.timing_ms["search"] / 24)


@needs_model
def test_rotation_search_returns_indices_into_the_callers_arrays(registrar) -> None:
    R = Rotation.from_euler("y", 120, degrees=True).as_matrix()
    source, target = asymmetric_blob(900, 3), asymmetric_blob(700, 4) @ R.T
    options = {"rotation_search": True, "working_size": 256, "keypoints": 64, "iterations": 2,
               "return_iterations": True}
    base = registrar.register(source, target, **options)
    assert ((base.source_index >= 0) & (base.source_index < 900)).all()
    assert ((base.target_index >= 0) & (base.target_index < 700)).all()
    assert base.source_index.dtype == base.target_index.dtype == np.int64
    assert len(base.source_index) == len(base.target_index) == len(base.credibility) == 64
    assert np.allclose(base.iteration_poses[-1].rotation, base.rotation)  # poses include the start rotation
    rng = np.random.default_rng(0)
    p, q = rng.permutation(900), rng.permutation(700)
    permuted = registrar.register(source[p], target[q], **options)
    np.testing.assert_array_equal(p[permuted.source_index], base.source_index)
    np.testing.assert_array_equal(q[permuted.target_index], base.target_index)
    np.testing.assert_allclose(permuted.transform, base.transform, atol=1e-5)


GENERAL = bundled_models_dir() / "general"


@pytest.mark.skipif(not (GENERAL / "manifest.json").exists(), reason="bundled model 'general' absent")
def test_with_a_refinement_general_searches_a_subsample_and_refines_the_full_clouds(monkeypatch) -> None:
    import service.stages.refine as refine_stage

    general = Registrar(GENERAL, threads=2)
    points, keypoints = general.manifest.search_subsample  # the export writes it for independent sampling
    assert (points, keypoints) == (SEARCH_POINTS, SEARCH_KEYPOINTS)
    embedded = spy_on_embedded_sizes(general, monkeypatch)
    refined: list[int] = []
    short: list[int] = []
    real_refine, real_many = refine_stage.refine_plane, refine_stage.refine_plane_many
    monkeypatch.setattr(refine_stage, "refine_plane", lambda src, *a, **k: refined.append(len(src)) or real_refine(
        src, *a, **k))  # the winner's full refinement
    monkeypatch.setattr(refine_stage, "refine_plane_many", lambda src, *a, **k: short.append(len(src)) or real_many(
        src, *a, **k))  # the kept candidates' short refinements, every third point
    R = Rotation.from_euler("y", 120, degrees=True).as_matrix()
    source, target = asymmetric_blob(900, 3), asymmetric_blob(700, 4) @ R.T
    found = general.register(source, target, rotation_search=True, refine="icp-plane", keypoints=128)
    assert embedded[0] == (1, points)  # the target's subsample, then the rotated sources' in chunks
    assert {n for _, n in embedded[1:]} == {points} and sum(b for b, _ in embedded[1:]) == 24
    assert set(short) == {256} and set(refined) == {768}  # the winner's on the full working source
    assert len(found.source_index) == len(found.target_index) == len(found.weight) == keypoints
    assert ((found.source_index >= 0) & (found.source_index < 900)).all()
    assert ((found.target_index >= 0) & (found.target_index < 700)).all()
    p, q = np.random.default_rng(0).permutation(900), np.random.default_rng(1).permutation(700)
    permuted = general.register(source[p], target[q], rotation_search=True, refine="icp-plane", keypoints=128)
    np.testing.assert_array_equal(p[permuted.source_index], found.source_index)
    np.testing.assert_array_equal(q[permuted.target_index], found.target_index)
    np.testing.assert_allclose(permuted.transform, found.transform, atol=1e-5)
    embedded.clear()
    general.register(source, target, rotation_search=True, refine="none", keypoints=128)
    assert {n for _, n in embedded} == {700, 768}  # without a refinement: the full working clouds


@needs_model
def test_a_model_trained_on_shared_points_searches_the_full_working_clouds(registrar, monkeypatch) -> None:
    assert registrar.manifest.search_subsample is None  # `clean`: the paper's shared points
    embedded = spy_on_embedded_sizes(registrar, monkeypatch)
    R = Rotation.from_euler("y", 120, degrees=True).as_matrix()
    found = registrar.register(asymmetric_blob(900, 3), asymmetric_blob(700, 4) @ R.T, rotation_search=True,
                               refine="icp-plane", keypoints=128)
    assert {n for _, n in embedded} == {700, 768} and len(found.source_index) == 128


@needs_model
def test_rotation_search_rejects_an_unsupported_size(registrar) -> None:
    cloud = asymmetric_blob(100)
    with pytest.raises(InputError, match="search_rotations"):
        registrar.register(cloud, cloud, rotation_search=True, search_rotations=7)


@needs_model
def test_rotation_search_with_icp_plane_refines_the_winner_point_to_plane(registrar, monkeypatch) -> None:
    import service.rotation_search as search_module
    import service.stages.refine as refine_stage
    from service.stages.ranking import CANDIDATE_SHIFTS

    calls: dict[str, int] = {"final_point": 0, "final_plane": 0}

    def counted(name, function):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return function(*args, **kwargs)

        return wrapper

    starts: list[int] = []

    def short_icps(src, tgt, R0, t0, **kwargs):
        starts.append(len(R0))
        return original_many(src, tgt, R0, t0, **kwargs)

    original_many = search_module.icp_many
    monkeypatch.setattr(search_module, "icp_many", short_icps)
    plane_iterations: list[int] = []
    real_plane = refine_stage.refine_plane
    monkeypatch.setattr(refine_stage, "icp", counted("final_point", refine_stage.icp))
    def plane(*args, **kwargs):
        plane_iterations.append(kwargs["max_iterations"])
        return real_plane(*args, **kwargs)

    monkeypatch.setattr(refine_stage, "refine_plane", counted("final_plane", plane))
    R = Rotation.from_euler("y", 120, degrees=True).as_matrix()
    source, target = asymmetric_blob(600, 3), asymmetric_blob(500, 4) @ R.T
    found = registrar.register(source, target, rotation_search=True, refine="icp-plane", working_size=256,
                               keypoints=64, iterations=2)
    # short ICPs stay point-to-point: all 24 starts after the first iteration, the SEARCH_KEEP kept after the last;
    # then point-to-plane only: a short refinement of each distinct kept candidate and of its rotation at up to
    # CANDIDATE_SHIFTS other translations (none if only one candidate), then the winner's full one
    assert starts == [24, search_module.SEARCH_KEEP] and calls["final_point"] == 0
    *short, final = plane_iterations
    assert final == 30 and set(short) <= {refine_stage.CANDIDATE_ITERATIONS}
    assert len(short) == 0 or 2 <= len(short) <= search_module.SEARCH_KEEP * (1 + CANDIDATE_SHIFTS)
    assert calls["final_plane"] == len(short) + 1
    assert "refine" in found.timing_ms and np.isfinite(found.transform).all()


def turned(candidate: SearchCandidate, degrees: float) -> SearchCandidate:
    """``candidate`` with its pose turned by ``degrees`` about x (a wrong basin)."""
    turn = Rotation.from_euler("x", degrees, degrees=True).as_matrix()
    return dataclasses.replace(candidate, rotation=turn @ candidate.rotation)


def search_returning(monkeypatch, make_candidates) -> None:
    """Make ``Registrar.register``'s search return ``make_candidates(the real candidates)``."""
    import service.stages.search as search_stage

    real = search_stage.search_hypotheses
    monkeypatch.setattr(search_stage, "search_hypotheses", lambda *a, **k: make_candidates(real(*a, **k)))


@needs_model
@pytest.mark.parametrize("refine", ["icp", "icp-plane"])
def test_with_a_refinement_the_search_candidates_are_ranked_again_after_short_refinements(
    registrar, monkeypatch, refine
) -> None:
    source, target, R, t = blob_pair(150.0)
    search_returning(monkeypatch, lambda found: [turned(found[0], 90.0), *found])  # a wrong basin ranked first
    result = registrar.register(source, target, refine=refine, rotation_search=True)
    assert angle_deg(result.rotation, R) < 2.0 and np.abs(result.translation - t).max() < 0.05
    search_returning(monkeypatch, lambda found: [turned(found[0], 90.0)])  # the same wrong basin alone
    wrong = registrar.register(source, target, refine=refine, rotation_search=True)
    assert angle_deg(wrong.rotation, R) > 30.0  # so the ranking above, not the refinement, found the right one
    assert wrong.inlier_ratio < result.inlier_ratio


@needs_model
def test_without_a_refinement_the_search_returns_its_own_best_candidate(registrar, monkeypatch) -> None:
    source, target, R, _ = blob_pair(150.0)
    search_returning(monkeypatch, lambda found: [turned(found[0], 90.0), *found])
    result = registrar.register(source, target, refine="none", rotation_search=True)
    assert angle_deg(result.rotation, R) > 30.0  # nothing to rank by: the first candidate is the answer


def test_distinct_candidates_drops_poses_in_the_same_basin() -> None:
    def candidate(degrees: float, shift: float) -> SearchCandidate:
        R = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
        return SearchCandidate(None, np.eye(3), R, np.array([shift, 0.0, 0.0]))  # output unused here

    candidates = [candidate(10, 0), candidate(10.5, 0.005), candidate(10, 0.05), candidate(40, 0), candidate(10.2, 0)]
    kept = distinct_candidates(candidates)
    assert kept == [candidates[0], candidates[2], candidates[3]]  # best first, order kept


@needs_model
def test_a_symmetric_shape_found_by_the_search_is_ambiguous_and_not_reliable(registrar, blob_150) -> None:
    """An ellipsoid's 180-degree flips about its axes fit as well as the true pose: the data cannot decide."""
    axis = np.array([0.48, 0.85, -0.21])
    R = Rotation.from_rotvec(np.radians(150) * axis / np.linalg.norm(axis)).as_matrix()
    source = ellipsoid_surface(np.random.default_rng(0), 1024, bump=0.0)
    target = ellipsoid_surface(np.random.default_rng(100), 1024, bump=0.0) @ R.T + [0.2, -0.1, 0.3]
    result = registrar.register(source, target, refine="icp-plane", rotation_search=True)
    assert result.inlier_ratio > 0.8  # it fits: only the ambiguity makes it unreliable
    assert not result.reliable
    assert any(w.startswith("ambiguous: a pose 180 deg away") for w in result.warnings)
    clear = blob_150(refine="icp-plane", rotation_search=True)  # the asymmetric shape: one pose fits
    assert clear.reliable and not any(w.startswith("ambiguous") for w in clear.warnings)


def test_ambiguity_needs_a_distant_pose_that_fits_almost_as_well() -> None:
    turn = Rotation.from_euler("z", [[0], [90], [5]], degrees=True).as_matrix()  # [3, 3, 3]: the best, far, near
    assert ambiguity_warning(turn, np.array([0.80, 0.78, 0.80]), 0).startswith("ambiguous: a pose 90 deg away")
    assert ambiguity_warning(turn, np.array([0.80, 0.70, 0.80]), 0) is None  # the near one does not count
    assert ambiguity_warning(turn, np.array([0.78, 0.80, 0.70]), 1).startswith("ambiguous: a pose 90 deg away")



@pytest.mark.parametrize(("fits", "words"), [([0.80, 0.78], "fits almost as well (inlier ratio 0.78 vs 0.80)"),
                                             ([0.80, 0.80], "fits as well (inlier ratio 0.80 vs 0.80)"),
                                             ([0.94, 1.00], "fits better (inlier ratio 1.00 vs 0.94)"),
                                             ([0.7999, 0.8004], "fits as well (inlier ratio 0.80 vs 0.80)")])
def test_the_ambiguity_warning_says_how_the_other_pose_fits(fits, words) -> None:
    """A check after the ranking can find a turn that fits better than the kept pose (the symmetry check's refined
    turns): the warning said it fitted "almost as well" at 1.00 against 0.94."""
    turn = Rotation.from_euler("z", [[0], [90]], degrees=True).as_matrix()  # [2, 3, 3]
    assert ambiguity_warning(turn, np.array(fits), 0) == f"ambiguous: a pose 90 deg away {words}; the shape may be " \
                                                         "symmetric"

# --- rotation_search="auto" -----------------------------------------------------------------------


def blob_pair(degrees: float, axis=(0.48, 0.85, -0.21)) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Source, target (800 of its 1024 points, rotated by ``degrees`` about ``axis`` and moved), R and t."""
    source = asymmetric_blob(1024, 1)
    axis = np.asarray(axis) / np.linalg.norm(axis)
    R = Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix()
    t = np.array([0.2, -0.1, 0.3])
    subset = np.random.default_rng(5).permutation(1024)[:800]
    return source, source[subset] @ R.T + t, R, t


def spy_on_search(monkeypatch) -> list[int]:
    """Count the calls of the rotation search made by ``Registrar.register``."""
    import service.stages.search as search_stage

    calls: list[int] = []
    real = search_stage.search_hypotheses

    def spy(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(search_stage, "search_hypotheses", spy)
    return calls


@needs_model
@pytest.mark.parametrize("refine", ["icp", "icp-plane"])
def test_auto_keeps_a_good_plain_result_without_searching(registrar, monkeypatch, refine) -> None:
    source, target, R, _ = blob_pair(20.0)
    plain = registrar.register(source, target, refine=refine, return_iterations=True)
    assert plain.reliable and not needs_search(plain)  # measured inlier ratio 0.94 (any attainable ratio), 0.03 deg
    calls = spy_on_search(monkeypatch)
    auto = registrar.register(source, target, refine=refine, return_iterations=True, rotation_search="auto")
    assert calls == [] and "search" not in auto.timing_ms and "search_per_hypothesis" not in auto.timing_ms
    np.testing.assert_array_equal(auto.transform, plain.transform)
    for name in ("source_index", "target_index", "credibility", "weight"):
        np.testing.assert_array_equal(getattr(auto, name), getattr(plain, name))
    assert (auto.inlier_ratio, auto.residual_rms, auto.reliable, auto.warnings) == (
        plain.inlier_ratio, plain.residual_rms, plain.reliable, plain.warnings)
    np.testing.assert_array_equal(auto.iteration_poses[-1].rotation, plain.iteration_poses[-1].rotation)
    assert angle_deg(auto.rotation, R) < 1.0


@needs_model
@pytest.mark.parametrize("refine", ["icp", "icp-plane"])
def test_auto_searches_when_the_plain_result_looks_wrong_and_recovers_150_degrees(blob_150, refine) -> None:
    _, _, R, t = blob_pair(150.0)  # the pair of the 150-degree test above
    plain = blob_150(refine=refine)
    assert angle_deg(plain.rotation, R) > 30.0 and needs_search(plain)  # measured: 100-120 deg, inliers 0.32-0.39

    auto = blob_150(refine=refine, rotation_search="auto")
    assert angle_deg(auto.rotation, R) < 2.0  # measured 0.03 (icp) / 0.008 (icp-plane) deg
    assert np.abs(auto.translation - t).max() < 0.05
    assert auto.reliable and auto.inlier_ratio > 0.9
    assert {"search", "search_per_hypothesis", "encoder", "refine", "total"} <= set(auto.timing_ms)
    assert auto.timing_ms["search_per_hypothesis"] == pytest.approx(auto.timing_ms["search"] / 24)
    assert auto.timing_ms["total"] >= auto.timing_ms["search"]
    searched = blob_150(refine=refine, rotation_search=True)
    np.testing.assert_array_equal(auto.transform, searched.transform)  # the search's winner, unchanged


@needs_model
def test_auto_never_searches_degenerate_clouds(registrar, monkeypatch) -> None:
    """Collinear points leave the rotation about their line open: no start rotation can fix that."""
    import service.stages.search as search_stage

    line = np.linspace(0.0, 1.0, 200)[:, None] * np.array([1.0, 2.0, 0.5])  # [200, 3]
    calls = spy_on_search(monkeypatch)
    monkeypatch.setattr(search_stage, "needs_search", lambda *_: True)  # however the result looks
    result = registrar.register(line, line + 0.1, refine="icp-plane", rotation_search="auto")
    assert calls == [] and "search" not in result.timing_ms
    assert not result.reliable and any("collinear" in w for w in result.warnings)


@needs_model
def test_auto_keeps_the_plain_result_when_it_ranks_before_the_searched_one(registrar, monkeypatch) -> None:
    import service.stages.search as search_stage

    real = search_stage.search_hypotheses

    def wrong_winner(*args, **kwargs):  # the search "finds" a pose 90 degrees off the plain one
        return [turned(real(*args, **kwargs)[0], 90.0)]

    monkeypatch.setattr(search_stage, "needs_search", lambda *_: True)  # search even a good result
    monkeypatch.setattr(search_stage, "search_hypotheses", wrong_winner)
    source, target, _, _ = blob_pair(20.0)
    options = {"working_size": 256, "keypoints": 64, "iterations": 2}
    plain = registrar.register(source, target, **options)
    auto = registrar.register(source, target, rotation_search="auto", **options)
    assert "search" in auto.timing_ms
    np.testing.assert_array_equal(auto.transform, plain.transform)
    assert auto.inlier_ratio == plain.inlier_ratio


@needs_model
def test_auto_returns_the_better_of_both_by_the_search_ranking(registrar, monkeypatch) -> None:
    import service.stages.search as search_stage

    monkeypatch.setattr(search_stage, "needs_search", lambda *_: True)  # search even a good result
    source, target, _, _ = blob_pair(20.0)
    options = {"working_size": 256, "keypoints": 64, "iterations": 2, "refine": "icp"}
    plain = registrar.register(source, target, **options)
    searched = registrar.register(source, target, rotation_search=True, **options)
    auto = registrar.register(source, target, rotation_search="auto", **options)
    best = min((plain, searched), key=lambda r: (-r.inlier_ratio, r.residual_rms))  # plain first on a tie
    np.testing.assert_array_equal(auto.transform, best.transform)
    assert "search" in auto.timing_ms


@needs_model
@pytest.mark.parametrize("value", ["yes", "on", "AUTO", 1, 0.5])
def test_rotation_search_rejects_values_other_than_true_false_or_auto(registrar, value) -> None:
    cloud = asymmetric_blob(100)
    with pytest.raises(InputError, match="rotation_search must be true, false or 'auto'"):
        registrar.register(cloud, cloud, rotation_search=value)
