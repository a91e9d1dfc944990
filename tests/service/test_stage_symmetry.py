"""The symmetry check on its own: a reliable pose of a shape that a half turn maps onto itself (an open tub) loses
``reliable`` with an ambiguity warning and keeps its pose; an asymmetric shape's stays reliable; a part of a shape of
revolution (an open bowl) whose stability is low is turned about its axis, 15, 60 and 120 deg either way (a bowl with
three fins fits itself turned 120 deg, not 60); ModelNet40 range scans of a bowl and a cone left 21-27 deg off about
the axis fit about as well turned 15 deg and are not reliable (the bowl's consensus then finds its right pose); a part
of a four-legged stool, whose centroid lies off the stool's axis, fits itself turned a quarter turn about that axis
and is flagged on a dense target (on a sparse one no quarter turn is tried); two views of a synthetic room that
overlap in part, at a wrong pose turned a quarter turn that overlays more of the source than the truth, are flagged
by a turn that fits what it overlays about as closely, and the truth is not; another such pose, which no turn fits
so, is flagged by a turn that fits the boxes (the points off the room's dominant planes) at least as closely; results
that are not reliable, or not refined, are not checked."""

from __future__ import annotations

import numpy as np
from pair_checks import needs_modelnet
from real_scan_cases import register_with_defaults
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob, room_scene
from stage_inputs import result_at, working_clouds

from bench.real_scans import Case, case_thresholds, turned
from bench.turntable_scans import modelnet_shapes, turntable_pairs
from service.manifest import bundled_models_dir
from service.registrar import Registrar
from service.rotation_search import rotation_between_deg
from service.stages import symmetry as stage
from service.stages.ranking import plane_frames_on_the_surface
from service.stages.symmetry import (
    AXIS_TURN_STABILITY,
    WHOLE_OVERLAY,
    axis_turns,
    frame_quarter_turns,
    half_turn_ambiguity,
    overlay_precision,
    placed_turns_ambiguity,
    quarter_turns,
    symmetry,
)

R_TRUE = Rotation.from_euler("zyx", [40.0, -20.0, 10.0], degrees=True).as_matrix()
T_TRUE = np.array([0.3, -0.2, 0.5])


def open_tub(points: int, seed: int) -> np.ndarray:
    """``[points, 3]`` on the floor and four walls of a 2 x 1 x 0.6 box without a lid: a half turn about its
    vertical axis maps it onto itself, no other rotation does."""
    rng = np.random.default_rng(seed)
    faces = [  # (origin, first edge, second edge): floor, the walls at x = 0 / 2, y = 0 / 1
        ((0, 0, 0), (2, 0, 0), (0, 1, 0)),
        ((0, 0, 0), (0, 1, 0), (0, 0, 0.6)),
        ((2, 0, 0), (0, 1, 0), (0, 0, 0.6)),
        ((0, 0, 0), (2, 0, 0), (0, 0, 0.6)),
        ((0, 1, 0), (2, 0, 0), (0, 0, 0.6)),
    ]
    area = np.array([np.linalg.norm(np.cross(a, b)) for _, a, b in faces])
    face = rng.choice(len(faces), size=points, p=area / area.sum())  # [points]
    o, a, b = (np.array([f[k] for f in faces], dtype=np.float64)[face] for k in range(3))  # [points, 3] each
    u, v = rng.random((2, points, 1))
    return o + u * a + v * b - np.array([1.0, 0.5, 0.3])


def open_bowl(points: int, seed: int) -> np.ndarray:
    """``[points, 3]`` on the side and floor of an open bowl about the z axis (radius 0.5 at the floor, 1.0 at the rim,
    0.8 deep): every turn about that axis maps it onto itself."""
    rng = np.random.default_rng(seed)
    side = int(0.75 * points)
    z, a = 0.8 * rng.random(side), 2 * np.pi * rng.random(side)  # [side] each
    r = 0.5 + 0.5 * z / 0.8
    floor_r, floor_a = 0.5 * np.sqrt(rng.random(points - side)), 2 * np.pi * rng.random(points - side)
    wall = np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)  # [side, 3]
    floor = np.stack([floor_r * np.cos(floor_a), floor_r * np.sin(floor_a), np.zeros(points - side)], axis=1)
    return np.concatenate([wall, floor]) - np.array([0.0, 0.0, 0.4])


def finned_bowl(points: int, seed: int) -> np.ndarray:
    """:func:`open_bowl` with three fins up its side at 0, 120 and 240 deg about the z axis (0.1 high, about 6 deg
    wide): a turn of 120 deg maps it onto itself, one of 60 deg does not."""
    bowl = open_bowl(points, seed)
    side = slice(0, int(0.75 * points))  # open_bowl's side points come first
    a = np.arctan2(bowl[side, 1], bowl[side, 0])  # [side]
    to_fin = np.angle(np.exp(3j * a)) / 3  # [side]: radians to the nearest fin
    bowl[side, :2] *= (1 + 0.1 * np.exp(-((to_fin / 0.1) ** 2)) / np.hypot(bowl[side, 0], bowl[side, 1]))[:, None]
    return bowl


def boxes_surface(boxes: list[tuple[tuple[float, ...], tuple[float, ...]]], points: int, seed: int) -> np.ndarray:
    """``[points, 3]`` on the faces of the axis-aligned ``boxes`` (lowest corner, highest corner), spread by area."""
    rng = np.random.default_rng(seed)
    faces = []  # (origin, first edge, second edge)
    for low, high in boxes:
        low, size = np.array(low), np.array(high) - np.array(low)
        for k in range(3):
            a, b = (np.eye(3)[(k + j) % 3] * size[(k + j) % 3] for j in (1, 2))
            faces += [(low, a, b), (low + size[k] * np.eye(3)[k], a, b)]
    area = np.array([np.linalg.norm(np.cross(a, b)) for _, a, b in faces])
    face = rng.choice(len(faces), size=points, p=area / area.sum())  # [points]
    o, a, b = (np.array([f[k] for f in faces])[face] for k in range(3))  # [points, 3] each
    u, v = rng.random((2, points, 1))
    return o + u * a + v * b


def four_legged_stool(points: int, seed: int) -> np.ndarray:
    """``[points, 3]`` on a stool: a square seat 1 x 1 x 0.1 on four square legs 0.1 wide under its corners, 0.9 high.
    A quarter turn about its vertical axis (z) maps it onto itself."""
    legs = [((x - 0.05, y - 0.05, -0.5), (x + 0.05, y + 0.05, 0.4)) for x in (-0.4, 0.4) for y in (-0.4, 0.4)]
    return boxes_surface([((-0.5, -0.5, 0.4), (0.5, 0.5, 0.5)), *legs], points, seed)


def bowl_part_on_bowl():
    """A part of one bowl cut off by a tilted plane (none of its principal axes is the bowl's), on a whole other sample
    of it moved by the true pose."""
    cut = np.array([0.6, 0.3, 0.5]) / np.linalg.norm([0.6, 0.3, 0.5])
    part = open_bowl(6000, 0)
    return working_clouds(part[part @ cut > -0.1], open_bowl(6000, 1) @ R_TRUE.T + T_TRUE)


def test_a_shape_a_half_turn_maps_onto_itself_is_ambiguous_and_keeps_its_pose():
    work, options = working_clouds(open_tub(3000, 0), open_tub(3000, 1) @ R_TRUE.T + T_TRUE)
    timing: dict[str, float] = {}
    checked = symmetry(work, result_at(R_TRUE, T_TRUE), options, timing)
    assert not checked.reliable
    assert len(checked.warnings) == 1 and checked.warnings[0].startswith("ambiguous: a pose 180 deg away")
    assert np.array_equal(checked.rotation, R_TRUE) and np.array_equal(checked.translation, T_TRUE)
    assert timing["postprocess"] > 0


def test_an_asymmetric_shape_stays_reliable():
    blob = asymmetric_blob(3000)
    work, options = working_clouds(blob, asymmetric_blob(3000, seed=1) @ R_TRUE.T + T_TRUE)
    assert half_turn_ambiguity(work, R_TRUE, T_TRUE, options) is None
    result = result_at(R_TRUE, T_TRUE)
    assert symmetry(work, result, options, {}) is result


def test_a_part_of_a_shape_of_revolution_is_turned_about_its_axis_where_its_stability_is_low(monkeypatch):
    work, options = bowl_part_on_bowl()
    turned = []  # one entry per time the pose was turned about its least constrained axis
    monkeypatch.setattr(stage, "axis_turns", lambda *args: turned.append(args) or axis_turns(*args))
    # stability unknown, or not below the bar: not turned about the axis; a quarter turn about one of the part's
    # principal axes, refined, reaches the bowl's surface all the same
    for stability in (None, AXIS_TURN_STABILITY):
        warning = half_turn_ambiguity(work, R_TRUE, T_TRUE, options, stability)
        assert warning is not None and warning.startswith("ambiguous: a pose")
    assert turned == []
    warning = half_turn_ambiguity(work, R_TRUE, T_TRUE, options, 0.5 * AXIS_TURN_STABILITY)
    assert warning is not None and warning.startswith("ambiguous: a pose") and len(turned) == 1
    checked = symmetry(work, result_at(R_TRUE, T_TRUE, stability=0.5 * AXIS_TURN_STABILITY), options, {})
    assert not checked.reliable and checked.warnings == [warning]
    assert np.array_equal(checked.rotation, R_TRUE)


def test_a_part_of_a_shape_a_turn_of_120_deg_maps_onto_itself_is_ambiguous():
    cut = np.array([0.6, 0.3, 0.5]) / np.linalg.norm([0.6, 0.3, 0.5])
    part = finned_bowl(6000, 0)
    work, options = working_clouds(part[part @ cut > -0.1], finned_bowl(6000, 1) @ R_TRUE.T + T_TRUE)
    warning = half_turn_ambiguity(work, R_TRUE, T_TRUE, options, 0.5 * AXIS_TURN_STABILITY)
    assert warning is not None and warning.startswith("ambiguous: a pose 120 deg away")


def test_a_part_of_a_shape_a_quarter_turn_maps_onto_itself_is_ambiguous_on_a_dense_target(monkeypatch):
    cut = np.array([0.6, 0.3, 0.5]) / np.linalg.norm([0.6, 0.3, 0.5])
    part = four_legged_stool(6000, 0)
    part = part[part @ cut > 0.0]  # its centroid lies off the stool's axis: a quarter turn about it leaves the stool
    work, options = working_clouds(part, four_legged_stool(6000, 1) @ R_TRUE.T + T_TRUE)  # 6,000 >= 4 x 768 points
    warning = half_turn_ambiguity(work, R_TRUE, T_TRUE, options)  # stability unknown: no axis turns
    assert warning is not None and warning.startswith("ambiguous: a pose 90 deg away")
    checked = symmetry(work, result_at(R_TRUE, T_TRUE), options, {})
    assert not checked.reliable and checked.warnings == [warning]
    assert np.array_equal(checked.rotation, R_TRUE) and np.array_equal(checked.translation, T_TRUE)
    turned = []  # one entry per time the pose was given its quarter turns
    monkeypatch.setattr(stage, "quarter_turns", lambda *args: turned.append(args) or quarter_turns(*args))
    work, options = working_clouds(part, four_legged_stool(2000, 1) @ R_TRUE.T + T_TRUE)  # as sparse as a sample
    assert half_turn_ambiguity(work, R_TRUE, T_TRUE, options) is None and turned == []


def test_a_room_view_turned_to_overlay_more_than_the_truth_is_ambiguous():
    room = room_scene(np.random.default_rng(1))  # floor and walls at x = 0, y = 0, x = 4 (4 x 3 m), eight boxes
    work, options = working_clouds(room[room[:, 0] < 3.2], room[room[:, 0] > 0.8])  # views overlapping on x in 0.8-3.2
    assert plane_frames_on_the_surface(work)
    # turned 90 deg about the vertical, the source's corner of walls x = 0 and y = 0 lies in the target's corner of
    # y = 0 and x = 4: it overlays more of the source than the truth (the identity) does, only the boxes disagree
    R_wrong, t_wrong = Rotation.from_euler("z", 90.0, degrees=True).as_matrix(), np.array([4.0, 0.0, 0.0])
    distances = stage.overlay_distances(work, np.stack([R_wrong, np.eye(3)]), np.stack([t_wrong, np.zeros(3)]))
    near, precision = overlay_precision(work, distances)
    assert near[1] < near[0] < WHOLE_OVERLAY and precision[1] > precision[0]
    warning = half_turn_ambiguity(work, R_wrong, t_wrong, options)
    assert warning is not None and "fits what it overlays about as closely" in warning
    checked = symmetry(work, result_at(R_wrong, t_wrong), options, {})
    assert not checked.reliable and checked.warnings == [warning] and np.array_equal(checked.rotation, R_wrong)
    assert half_turn_ambiguity(work, np.eye(3), np.zeros(3), options) is None  # the truth stays reliable


def test_a_room_view_turned_a_quarter_turn_is_ambiguous_by_what_is_not_wall_or_floor():
    room = room_scene(np.random.default_rng(0))  # floor and walls at x = 0, y = 0, x = 4 (4 x 3 m), eight boxes
    work, options = working_clouds(room[room[:, 0] < 3.2], room[room[:, 0] > 0.8])  # views overlapping on x in 0.8-3.2
    # turned 90 deg about the vertical, the source's corner of walls x = 0 and y = 0 lies in the target's corner of
    # y = 0 and x = 4; no turn fits what it overlays within PRECISION_GAP of it, but the boxes land off the target's
    R_wrong, t_wrong = Rotation.from_euler("z", 90.0, degrees=True).as_matrix(), np.array([4.0, 0.0, 0.0])
    warning = half_turn_ambiguity(work, R_wrong, t_wrong, options)
    assert warning is not None and "fits what is not wall or floor at least as closely" in warning
    checked = symmetry(work, result_at(R_wrong, t_wrong), options, {})
    assert not checked.reliable and checked.warnings == [warning] and np.array_equal(checked.rotation, R_wrong)
    assert half_turn_ambiguity(work, np.eye(3), np.zeros(3), options) is None  # the truth stays reliable
    points = work.working_source  # [Ns, 3]: the room's own coordinates
    off = stage.off_plane_points(points, work.inlier_distance)  # [Ns]
    assert 0.1 < off.mean() < 0.3  # the boxes' points away from floor and walls
    assert (np.abs(points[off]).min(axis=1) > 2.0 * work.inlier_distance).all()  # none near floor or wall
    distances = stage.overlay_distances(work, np.stack([R_wrong, np.eye(3)]), np.stack([t_wrong, np.zeros(3)]))
    amount, precision = overlay_precision(work, distances, off)
    assert (amount > stage.MIN_STRUCTURE).all() and precision[1] > precision[0] + 0.5  # the truth fits the boxes


def test_a_room_view_a_quarter_turn_off_its_place_is_ambiguous_by_its_turns_at_their_best_translations(monkeypatch):
    room = room_scene(np.random.default_rng(56))  # floor and walls at x = 0, y = 0, x = 4 (4 x 3 m), eight boxes
    work, options = working_clouds(room[room[:, 0] < 3.2], room[room[:, 0] > 0.8])  # views overlapping on x in 0.8-3.2
    # the source's corner of walls x = 0 and y = 0 in the target's corner of y = 0 and x = 4, as the pipeline returns
    # this room turned: the turns about the moved source's centroid, briefly refined, stay off the truth, and none
    # of them fits the boxes as closely as the pose
    R_wrong, t_wrong = Rotation.from_euler("z", 90.0, degrees=True).as_matrix(), np.array([4.0, 0.0, 0.0])
    with monkeypatch.context() as patched:
        patched.setattr(stage, "placed_turns_ambiguity", lambda *args: None)
        assert half_turn_ambiguity(work, R_wrong, t_wrong, options) is None
    # one of its quarter turns about the walls' and floor's normals has the truth's rotation (the identity) ...
    turns = frame_quarter_turns(work, R_wrong, t_wrong)
    assert len(turns) == 6 and min(rotation_between_deg(np.eye(3), R) for R, _ in turns) < 3.0
    # ... and at its best translation it fits the boxes more closely than the pose: the result is ambiguous
    warning = half_turn_ambiguity(work, R_wrong, t_wrong, options)
    assert warning is not None and warning.startswith("ambiguous: a pose 90 deg away fits what is not wall or floor")
    distance = stage.icp_distance(work, options)
    placed = placed_turns_ambiguity(work, R_wrong, t_wrong, options.refine_mode, distance, work.target_surface)
    assert placed == warning
    assert half_turn_ambiguity(work, np.eye(3), np.zeros(3), options) is None  # the truth stays reliable
    near, _ = overlay_precision(work, stage.overlay_distances(work, R_wrong[None], t_wrong[None]))
    monkeypatch.setattr(stage, "WHOLE_OVERLAY", near[0])  # a pose that overlays its whole source is not tested
    assert placed_turns_ambiguity(work, R_wrong, t_wrong, options.refine_mode, distance, work.target_surface) is None


def test_the_registrar_does_not_call_a_room_view_a_quarter_turn_off_reliable():
    """The room above, its source view turned as one of the synthetic rooms of decision 0088 was: the pipeline returns
    it a quarter turn off (89.8 deg), which without the turns at their best translations was `reliable`."""
    room = room_scene(np.random.default_rng(56))
    source, target = room[room[:, 0] < 3.2], room[room[:, 0] > 0.8]
    turn = Rotation.from_euler("zyx", [119.0, 34.4, 115.8], degrees=True).as_matrix()
    centre = source.mean(axis=0)
    result = Registrar(bundled_models_dir() / "general", threads=1).register(
        ((source - centre) @ turn.T + centre).astype(np.float32), target.astype(np.float32), refine="icp-plane",
        rotation_search="auto")
    R_src = result.rotation @ turn  # the returned pose of the unturned view
    degrees = np.degrees(np.arccos(np.clip((np.trace(R_src) - 1) / 2, -1.0, 1.0)))
    assert degrees < 5.0 or not result.reliable, (degrees, result.warnings)


def test_the_off_plane_points_from_the_shared_frame_are_those_of_the_working_source_under_a_guess():
    room = room_scene(np.random.default_rng(0))
    guess = np.eye(4)
    guess[:3, :3], guess[:3, 3] = Rotation.from_euler("zyx", [70.0, -25.0, 40.0], degrees=True).as_matrix(), [1, 2, 3]
    work, _ = working_clouds(room[room[:, 0] < 3.2], room[room[:, 0] > 0.8], {"initial_transform": guess.tolist()})
    shared = work.source_frame.turned_back(work.R_init)  # found on src_n, which the guess turned
    alone = stage.off_plane_points(work.working_source, work.inlier_distance)  # [Ns] its own frame, afresh
    assert 0.1 < alone.mean() < 0.3
    assert np.array_equal(stage.off_plane_points(work.working_source, work.inlier_distance, shared), alone)


def test_overlay_precision_is_the_close_fit_among_the_points_overlaid():
    blob = asymmetric_blob(3000)
    work, _ = working_clouds(blob, blob @ R_TRUE.T + T_TRUE)
    far = T_TRUE + 100.0  # nothing overlaid
    near, precision = overlay_precision(work, stage.overlay_distances(work, np.stack([R_TRUE, R_TRUE]),
                                                                       np.stack([T_TRUE, far])))
    assert np.allclose(near, [1.0, 0.0]) and np.allclose(precision, [1.0, 0.0])


def test_quarter_turns_turn_the_pose_90_deg_either_way_about_the_moved_points_principal_axes():
    points = open_tub(3000, 0)  # principal axes x, y, z (2 x 1 x 0.6)
    R_q, t_q = quarter_turns(points, R_TRUE, T_TRUE)
    assert R_q.shape == (6, 3, 3) and t_q.shape == (6, 3)
    centre = (points @ R_TRUE.T + T_TRUE).mean(axis=0)
    for k, (R, t) in enumerate(zip(R_q, t_q, strict=True)):
        turn = Rotation.from_matrix(R @ R_TRUE.T).as_rotvec(degrees=True)  # [3]
        axis = R_TRUE[:, k // 2]  # the tub's x, y, z after the true pose
        assert abs(np.linalg.norm(turn) - 90.0) < 1e-6 and abs(abs(turn @ axis) / 90.0 - 1.0) < 1e-3
        assert np.linalg.norm(R @ (R_TRUE.T @ (centre - T_TRUE)) + t - centre) < 1e-9  # the centroid stays
    for k in range(3):  # either way: the two turns about one axis undo each other
        assert np.allclose((R_q[2 * k] @ R_TRUE.T) @ (R_q[2 * k + 1] @ R_TRUE.T), np.eye(3), atol=1e-12)


def test_axis_turns_turn_the_pose_15_60_and_120_deg_either_way_about_the_axis_of_revolution():
    work, _ = bowl_part_on_bowl()
    axis = R_TRUE[:, 2]  # the bowl's axis after the true pose, through T_TRUE + R_TRUE (0, 0, -0.4)
    turns = axis_turns(work, R_TRUE, T_TRUE)
    assert len(turns) == 6
    for (R, t), degrees in zip(turns, (15.0, 15.0, 60.0, 60.0, 120.0, 120.0), strict=True):
        turn = Rotation.from_matrix(R @ R_TRUE.T).as_rotvec(degrees=True)  # [3]
        assert abs(np.linalg.norm(turn) - degrees) < 1e-6 and abs(abs(turn @ axis) / degrees - 1.0) < 1e-3
        on_axis = T_TRUE + R_TRUE @ np.array([0.0, 0.0, -0.4])  # a point of the axis stays where it was
        assert np.linalg.norm(R @ (R_TRUE.T @ (on_axis - T_TRUE)) + t - on_axis) < 0.01


def registered_turntable_case(shape_class: str, index: int, angle: float, rng: np.random.Generator, draw: int
                              ) -> tuple[list[str], bool, bool]:
    """``bench.turntable_scans``' pair of the ``index``-th test shape of ``shape_class`` scanned at 0 and ``angle`` deg,
    its source turned by the ``draw``-th rotation drawn from ``rng`` (as ``pair_cases`` draws them pair after pair),
    registered by ``general`` with the service's defaults (:func:`real_scan_cases.register_with_defaults`) -> the
    warnings, whether it is right and whether it is reliable."""
    angles = [24.0, 48.0]  # the bench's default angles: one rng scans 0 deg, then each in turn
    scanned = angles[: angles.index(angle) + 1]  # so the angles after this one change nothing: not scanned
    pair = turntable_pairs(modelnet_shapes([shape_class], 2)[index], scanned)[-1]
    rotation = [Rotation.random(random_state=rng) for _ in range(draw)][-1].as_matrix()
    source, truth = turned(pair.source, pair.src_to_tgt, rotation)
    case = Case(pair.name, pair.sensor, f"turned, draw {draw}", 1.0, source, pair.target, truth)
    result, rotation_error, translation_error = register_with_defaults(case)
    max_degrees, max_distance = case_thresholds(case)
    return result.warnings, rotation_error < max_degrees and translation_error < max_distance, result.reliable


@needs_modelnet
def test_a_scanned_cone_left_turned_about_its_axis_is_not_reliable_where_a_15_deg_turn_fits_as_well():
    """The second test cone scanned 0 and 48 deg apart on the turntable, its source turned (the eighth rotation of
    seed 1's second turns: the ten other classes' run of ``bench.turntable_scans``), is registered 27 deg off about the
    cone's axis at a stability of 0.02 (close fit 0.76): its turns of 60 and 120 deg about that axis fit worse, but
    the turn of 15 deg, refined, fits within 0.03 of the pose (0.74), 19 deg from it."""
    warnings, right, reliable = registered_turntable_case("cone", 1, 48.0, np.random.default_rng([1, 1]), 8)
    assert right or not reliable
    if not right:  # flagged by a turn about the axis, not by a half or a quarter turn
        flags = [w for w in warnings if w.startswith("ambiguous: a pose ")]
        assert len(flags) == 1 and int(flags[0].split()[3]) < 45, warnings


@needs_modelnet
def test_a_scanned_bowl_a_15_deg_turn_calls_ambiguous_is_settled_by_the_descriptors():
    """The first test bowl scanned 0 and 24 deg apart, its source turned (seed 1's first rotation), is refined to a pose
    21 deg off that a turn of 15 deg about its least constrained axis fits more closely: no longer ``reliable``, the
    result goes to the descriptor consensus, whose pose is right and confirmed. Where ONNX Runtime's kernels round
    otherwise (AVX-512 against AVX2), the refinement reaches the right pose itself, with no warning."""
    warnings, right, reliable = registered_turntable_case("bowl", 0, 24.0, np.random.default_rng(1), 1)
    assert right and reliable
    assert not warnings or any(w.startswith("descriptor consensus") for w in warnings), warnings


def test_an_asymmetric_shape_has_no_free_turn_to_try():
    blob = asymmetric_blob(3000)
    work, options = working_clouds(blob, asymmetric_blob(3000, seed=1) @ R_TRUE.T + T_TRUE)
    assert half_turn_ambiguity(work, R_TRUE, T_TRUE, options, 0.5 * AXIS_TURN_STABILITY) is None


def test_results_not_reliable_or_not_refined_are_not_checked():
    tub = open_tub(3000, 0)
    work, options = working_clouds(tub, open_tub(3000, 1) @ R_TRUE.T + T_TRUE)
    unreliable = result_at(R_TRUE, T_TRUE, reliable=False)
    assert symmetry(work, unreliable, options, {}) is unreliable
    work, options = working_clouds(tub, open_tub(3000, 1) @ R_TRUE.T + T_TRUE, {"refine": "none"})
    unrefined = result_at(R_TRUE, T_TRUE)
    timing: dict[str, float] = {}
    assert symmetry(work, unrefined, options, timing) is unrefined and "postprocess" not in timing


def test_the_registrar_does_not_call_a_symmetric_shape_reliable():
    registrar = Registrar(bundled_models_dir() / "general", threads=1)
    result = registrar.register(
        open_tub(3000, 0), open_tub(3000, 1) @ R_TRUE.T + T_TRUE, refine="icp-plane", rotation_search="auto"
    )
    assert not result.reliable
    assert any(w.startswith("ambiguous") for w in result.warnings)


def closed_tank(rng: np.random.Generator, points: int) -> np.ndarray:
    """``[N, 3]``: a cylinder 2 long and 1 across (its side lightly noisy) with both end caps: round about z, without
    features."""
    side = int(points * 0.7)
    z, a = rng.uniform(0.0, 2.0, side), rng.uniform(0.0, 2 * np.pi, side)
    wall = np.c_[0.5 * np.cos(a), 0.5 * np.sin(a), z] + rng.normal(0.0, 0.002, (side, 3))
    k = points - side
    r, b = 0.5 * np.sqrt(rng.uniform(0.0, 1.0, k)), rng.uniform(0.0, 2 * np.pi, k)
    return np.r_[wall, np.c_[r * np.cos(b), r * np.sin(b), np.where(rng.uniform(size=k) < 0.5, 0.0, 2.0)]]


def test_a_withdrawn_result_drops_the_note_that_confirmed_it():
    """A tank turned 50 deg about its axis: the descriptors confirm a pose the symmetry check then finds ambiguous; the
    note 'confirmed by descriptors' stood beside the refusal."""
    registrar = Registrar(bundled_models_dir() / "general")
    rng = np.random.default_rng(50)
    R = Rotation.from_rotvec([0.0, 0.0, np.radians(50)]).as_matrix()
    source = closed_tank(rng, 4000)
    target = closed_tank(rng, 4000) @ R.T + [0.3, -0.2, 0.1]
    result = registrar.register(source, target, refine="icp-plane", rotation_search="auto")  # the service's defaults
    kinds = [w.split(":")[0] for w in result.warnings]
    assert not result.reliable and "ambiguous" in kinds, result.warnings
    assert "confirmed by descriptors" not in kinds and "confirmed by free space" not in kinds, result.warnings
