"""Stage 9, symmetry check: a ``reliable`` result whose half turns fit almost as well is ambiguous.

A near-symmetric shape (a bathtub, a bench) seen from two views overlays the target about as well
turned half a turn about one of its axes: the inlier ratio and the close fit cannot tell the two poses apart, and a
search that never reached the other basin has no close second to flag (:func:`service.rotation_search.ambiguity_warning`
needs one). So the final pose of a result about to be called ``reliable`` competes with its three half turns about the
moved working source's principal axes (:func:`service.stages.partial.half_turns`), each briefly refined as the search's
candidates are (:func:`service.stages.refine.short_refine`), ranked by the fit the search ranks by
(:func:`service.stages.ranking.candidate_fits`); one within ``AMBIGUOUS_RATIO_GAP`` of the pose's fit, or above it,
makes the result ambiguous: not ``reliable``, with a warning. The pose itself is kept
(``docs/decisions/0030-half-turn-symmetry-check.md``).

A shape of revolution seen in part (a vase, a bowl) turns about its axis without leaving its surface, and the axis
need not be a principal axis of the part seen. Where the result's ``stability`` is low and its least constrained
motion is a turn (:mod:`service.stability`), the pose also competes with itself turned by each of ``AXIS_TURN_DEGREES``
either way about that motion's axis (``docs/decisions/0038-turns-about-the-least-constrained-axis.md``,
``0073-turns-of-120-deg-about-the-least-constrained-axis.md``). The turn of 15 deg catches a round object left 20-30
deg off about its axis, which fits about as well turned 15 deg and refined
(``0097-turns-of-15-deg-about-the-least-constrained-axis.md``).

A shape with four-fold symmetry (a four-legged stool, a square table or box) overlays its target about as well turned a
quarter turn about its vertical axis, which is often a principal axis of the part seen, at a stability that need not
be low. So where the entered target samples the surface densely (a scan, not a sample as sparse as the working cloud:
:func:`service.stages.ranking.samples_the_surface`) the pose also competes with its :func:`quarter_turns` about the
same principal axes as its half turns. A quarter turn about the part seen's centroid leaves it off the symmetry axis
by up to the object's radius, which the short refinement does not close in its few updates: the best-fitting quarter
turn is refined ``QUARTER_TURN_ITERATIONS`` updates more before the ranking. On 768-point targets the turns would have
taken a default request to 1.16x its p50 (``docs/decisions/0076-quarter-turns-in-the-symmetry-check.md``).

Where the clouds are rooms (orthogonal planes over a dense target:
:func:`service.stages.search.plane_frames_on_the_surface`) and the pose places part of its source off the target
(less than ``WHOLE_OVERLAY`` of the working source within ``NEAR_DISTANCE`` inlier distances of the entered target),
the fit comparison can favour a wrong pose: of two fragments that overlap in part, a half- or quarter-turned pose may
overlay more of the source than the truth does, and the close fit counts the points overlaid. So there a turn also
makes the result ambiguous where it fits within ``PARTIAL_FIT_GAP`` of the pose's close fit and fits what it overlays
about as closely (:func:`overlay_precision`: the close-fit share among the source points it places near the target,
which the size of the overlap does not raise; at least the pose's less ``PRECISION_GAP``). On the rooms measured, a
right result's turns within ``PARTIAL_FIT_GAP`` of its fit fit what they overlay at least 0.17 less closely than the
pose. A pose that overlays its whole source is not tested: there a turn that overlays less is worse, whatever it
fits (a scanned lamp's turns fit what they overlay within 0.01 of its right pose while overlaying 0.91 of it)
(``docs/decisions/0077-partial-overlays-in-the-symmetry-check.md``).

Walls and floor give a room's pose only up to the symmetries of its frame: turned a quarter turn, the source's
corner of two walls lies in another corner of the target, and a pose so turned may overlay more of the source than
the truth and fit it nearly as closely. What tells places apart is what is not wall or floor (furniture, boxes,
clutter). So where the precision comparison flags nothing, the same rooms compare the pose and its turns by their
structure precision: the close-fit share among the working source's :func:`off_plane_points` (farther than
``OFF_PLANE_DISTANCE`` inlier distances from each of the source's dominant planes) that a pose places near the
target. A turn more than ``AMBIGUOUS_DEGREES`` away that, as the pose does, places at least ``MIN_STRUCTURE`` of the
working source's points off the planes and near the target, and fits them at least as closely as the pose (its
structure precision at least the pose's less ``STRUCTURE_GAP``) makes the result ambiguous. On the rooms measured, a
right result's best such turn fits them at least 0.08 less closely than the pose; at the wrong poses measured
(synthetic rooms turned a quarter turn, a room crop 16 deg off) a turn fits them 0.02-0.30 more closely
(``docs/decisions/0079-what-is-not-wall-or-floor-in-the-symmetry-check.md``).

The turns above are about the principal axes of the part seen, which in a room view need not be its walls' normals,
and through its centroid: where one view's corner lies in another corner of the target, the right place lies about
a metre from any of them, and the short refinement slides along the walls instead of reaching it. So where neither
comparison flags the pose of such rooms, it is also compared by its structure precision alone with its quarter turns
about the normals of the source's walls and floor (:func:`frame_quarter_turns`), each at its rotation's best
candidate translations (:func:`service.stages.ranking.with_translations`, as the search's candidates and the flip
check's half turns are) and briefly refined (:func:`placed_turns_ambiguity`;
``docs/decisions/0088-quarter-turns-at-their-best-translations.md``).
"""

from __future__ import annotations

import time

import numpy as np

from service.icp import Surface, rotation_of
from service.options import RegistrationOptions
from service.plane_frames import AXIS_DEGREES, CloudFrame, cloud_frame
from service.result import RegistrationResult
from service.rotation_search import AMBIGUOUS_DEGREES, ambiguity_warning, rotation_between_deg
from service.stability import ROTATION_SHARE, pose_stability
from service.stages.normalise import ICP_DISTANCE, Working
from service.stages.partial import half_turns, principal_frame
from service.stages.ranking import (
    CLOSE_FIT,
    candidate_fits,
    plane_frames_on_the_surface,
    samples_the_surface,
    with_translations,
)
from service.stages.refine import icp_distance, short_refine
from service.stages.withdraw import withdrawn

AXIS_TURN_STABILITY = 0.05  # below this stability a result also competes with turns about its least constrained axis
AXIS_TURN_DEGREES = (15.0, 60.0, 120.0)  # ... by each of these angles either way
QUARTER_TURN_ITERATIONS = 5  # more short-refinement updates for the best-fitting of the quarter turns
# rooms whose pose overlays part of its source: a turn within PARTIAL_FIT_GAP of the pose's close fit whose
# overlay_precision is at least the pose's less PRECISION_GAP makes the result ambiguous
NEAR_DISTANCE = 3.0  # inlier distances: a working source point this near the entered target is overlaid
WHOLE_OVERLAY = 0.99  # a pose that overlays at least this share of the working source is not tested so
PARTIAL_FIT_GAP = 0.2
PRECISION_GAP = 0.05
# ... and a turn that fits the source's points off its dominant planes at least as closely as the pose does
PLANE_SHARE = 0.05  # a slab across a plane-frame axis holding this share of the working source is a dominant plane
PLANE_SLAB = 1.0  # inlier distances: the width of the bins a dominant plane's slab (two adjacent bins) is sought in
OFF_PLANE_DISTANCE = 2.0  # inlier distances: a working source point farther than this from each dominant plane is off
MIN_STRUCTURE = 0.05  # share of the working source: off-plane points a pose places near the target, for a comparison
STRUCTURE_GAP = 0.0


def symmetry(
    work: Working, result: RegistrationResult, options: RegistrationOptions, timing: dict[str, float]
) -> RegistrationResult:
    """``result``, not ``reliable`` and with :func:`half_turn_ambiguity`'s warning where it gives one; only results
    that are ``reliable`` and refined are checked. The time is added to ``timing["postprocess"]``."""
    if not result.reliable or options.refine_mode == "none":
        return result
    started = time.perf_counter()
    warning = half_turn_ambiguity(work, result.rotation, result.translation, options, result.stability)
    timing["postprocess"] = timing.get("postprocess", 0.0) + 1000 * (time.perf_counter() - started)
    if warning is None:
        return result
    return withdrawn(result, warning)


def half_turn_ambiguity(
    work: Working, R: np.ndarray, t: np.ndarray, options: RegistrationOptions, stability: float | None = None
) -> str | None:
    """The ambiguity warning of the pose ``R [3, 3], t [3]`` (caller's units) against its three half turns, where the
    entered target samples the surface densely its six :func:`quarter_turns`, and where ``stability`` is below
    ``AXIS_TURN_STABILITY`` its :func:`axis_turns`, after the search's short refinement (the best-fitting quarter turn
    ``QUARTER_TURN_ITERATIONS`` updates more); on rooms also :func:`partial_overlay_ambiguity`'s and
    :func:`placed_turns_ambiguity`'s; or ``None`` where each of them fits worse by more than ``AMBIGUOUS_RATIO_GAP``
    or returns to the pose."""
    mode = options.refine_mode
    surface = work.target_surface if mode != "icp" else None
    distance = icp_distance(work, options)
    R_h, t_h = half_turns(work.working_source, R, t)  # [3, 3, 3], [3, 3]
    quarters = list(zip(*quarter_turns(work.working_source, R, t), strict=True)) if samples_the_surface(work) else []
    starts = list(zip(R_h, t_h, strict=True)) + quarters
    if stability is not None and stability < AXIS_TURN_STABILITY:
        starts += axis_turns(work, R, t, surface)
    R_s, t_s = short_refine(work, starts, mode, distance, surface)
    rotations = np.concatenate([R[None], R_s])  # [1 + C, 3, 3]: the pose, then its turns
    translations = np.concatenate([t[None], t_s])  # [1 + C, 3]
    fits, measure = candidate_fits(work, rotations, translations)  # [1 + C]
    if quarters:  # the best-fitting quarter turn, refined further
        best = 1 + len(R_h) + int(np.argmax(fits[1 + len(R_h) : 1 + len(R_h) + len(quarters)]))  # its row
        R_b, t_b = short_refine(
            work, [(rotations[best], translations[best])], mode, distance, surface, QUARTER_TURN_ITERATIONS
        )
        rotations[best], translations[best] = R_b[0], t_b[0]
        fits[best] = candidate_fits(work, R_b, t_b)[0][0]
    warning = ambiguity_warning(rotations, fits, 0, measure=measure)
    if warning is None and plane_frames_on_the_surface(work):
        warning = partial_overlay_ambiguity(work, rotations, translations, fits)
        if warning is None:
            warning = placed_turns_ambiguity(work, R, t, mode, distance, surface)
    return warning


def frame_quarter_turns(work: Working, R: np.ndarray, t: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pose ``R [3, 3], t [3]`` of the working source turned 90 deg either way about each axis of its plane frame
    (the normals of its walls and floor, moved by the pose), through the moved points' centroid; none where the
    source has no plane frame."""
    axes = work.source_frame.turned_back(work.R_init).axes  # [3, 3] columns, the working source's own frame
    if axes is None:
        return []
    centre = (work.working_source @ R.T + t).mean(axis=0)  # [3]
    turns = [rotation_of(sign * 0.5 * np.pi * axis, 0.5 * np.pi) for axis in (R @ axes).T for sign in (1.0, -1.0)]
    return [(turn @ R, turn @ (t - centre) + centre) for turn in turns]


def placed_turns_ambiguity(work: Working, R: np.ndarray, t: np.ndarray, mode: str, distance: float,
                           surface: Surface | None) -> str | None:
    """:func:`structure_ambiguity`'s warning of a room's pose ``R [3, 3], t [3]`` (caller's units) against its
    :func:`frame_quarter_turns` at their rotations' best candidate translations, each briefly refined; ``None`` where
    the pose overlays at least ``WHOLE_OVERLAY`` of its working source (the gate of :func:`partial_overlay_ambiguity`)
    or no such translation is found."""
    pose_distances = overlay_distances(work, R[None], t[None])  # [1, Ns]
    if overlay_precision(work, pose_distances)[0][0] >= WHOLE_OVERLAY:
        return None
    turns = frame_quarter_turns(work, R, t)
    placed = with_translations(work, turns)[0][len(turns):]  # the turns' rotations at other places only
    if not placed:
        return None
    R_s, t_s = short_refine(work, placed, mode, distance, surface)  # [C, 3, 3], [C, 3]
    rotations = np.concatenate([R[None], R_s])  # [1 + C, 3, 3]: the pose, then the placed turns
    distances = np.concatenate([pose_distances, overlay_distances(work, R_s, t_s)])  # [1 + C, Ns]
    return structure_ambiguity(work, rotations, distances)


def overlay_distances(work: Working, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """``[C, Ns]``: each working source point's distance to the entered target at each pose (``rotations [C, 3, 3]``,
    ``translations [C, 3]``, caller's units), ``inf`` beyond ``NEAR_DISTANCE`` inlier distances; one KD-tree query for
    :func:`overlay_precision` of every point and of the :func:`off_plane_points` alike."""
    reach = NEAR_DISTANCE * work.inlier_distance
    moved = work.working_source @ rotations.transpose(0, 2, 1) + translations[:, None]  # [C, Ns, 3]
    dist, _ = work.entered_target_tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=reach)
    return dist.reshape(moved.shape[:2])


def overlay_precision(work: Working, distances: np.ndarray, rows: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """For each pose, from its working source points' ``distances [C, Ns]`` (:func:`overlay_distances`), of the
    points ``rows`` (bool ``[Ns]``; all where ``None``): ``near [C]``, the share of the whole working source that is
    among them and within ``NEAR_DISTANCE`` inlier distances of the entered target (what the pose overlays), and
    ``precision [C]``, the share of those within ``CLOSE_FIT`` inlier distances (how closely it fits what it
    overlays: :func:`service.stages.ranking.close_fit` over ``near``; 0 where it overlays none)."""
    taken = distances if rows is None else distances[:, rows]  # [C, K]
    near = np.count_nonzero(taken < NEAR_DISTANCE * work.inlier_distance, axis=1)  # [C]
    close = np.count_nonzero(taken < CLOSE_FIT * work.inlier_distance, axis=1)  # [C]
    return near / distances.shape[1], np.divide(close, near, out=np.zeros(len(near)), where=near > 0)


def partial_overlay_ambiguity(
    work: Working, rotations: np.ndarray, translations: np.ndarray, fits: np.ndarray
) -> str | None:
    """The warning of a pose (row 0 of ``rotations [1 + C, 3, 3]``, ``translations [1 + C, 3]``, close fits ``fits
    [1 + C]``) that overlays part of its source (below ``WHOLE_OVERLAY``) against its refined turns (the other rows):
    the turn more than ``AMBIGUOUS_DEGREES`` from it with the best :func:`overlay_precision` among those within
    ``PARTIAL_FIT_GAP`` of its close fit and at least its precision less ``PRECISION_GAP``; where none is,
    :func:`structure_ambiguity`'s warning (``None`` where it gives none)."""
    distances = overlay_distances(work, rotations, translations)  # [1 + C, Ns]
    near, precision = overlay_precision(work, distances)  # [1 + C] each
    if near[0] >= WHOLE_OVERLAY:
        return None
    for i in np.argsort(-precision[1:], kind="stable") + 1:
        angle = rotation_between_deg(rotations[0], rotations[i])
        if angle > AMBIGUOUS_DEGREES and fits[i] >= fits[0] - PARTIAL_FIT_GAP:
            if precision[i] < precision[0] - PRECISION_GAP:
                break  # the others fit what they overlay less closely still
            return (
                f"ambiguous: a pose {angle:.0f} deg away fits what it overlays about as closely (close fit "
                f"{precision[i]:.2f} vs {precision[0]:.2f} of the source points each places near the target) and "
                f"overlays {near[i]:.2f} of the source vs {near[0]:.2f}; the clouds may overlap in part"
            )
    return structure_ambiguity(work, rotations, distances)


def structure_ambiguity(work: Working, rotations: np.ndarray, distances: np.ndarray) -> str | None:
    """The warning of a room's pose (row 0 of ``rotations [1 + C, 3, 3]``; its working source points' distances
    to the target ``distances [1 + C, Ns]``, :func:`overlay_distances`) against its refined turns (the other rows) by
    what is not wall or floor: the turn more than ``AMBIGUOUS_DEGREES`` from it with the best structure precision
    (:func:`overlay_precision` of the :func:`off_plane_points`) among those that, like the pose, place at least
    ``MIN_STRUCTURE`` of the working source's points off its dominant planes and near the target, where that is at
    least the pose's less ``STRUCTURE_GAP``; ``None`` where none is, or the pose places too few such points near the
    target."""
    frame = work.source_frame.turned_back(work.R_init)  # src_n's directions in the working source's own frame
    off = off_plane_points(work.working_source, work.inlier_distance, frame)  # [Ns]
    amount, precision = overlay_precision(work, distances, off)  # [1 + C] each
    if amount[0] < MIN_STRUCTURE:
        return None
    angles = np.array([rotation_between_deg(rotations[0], Q) for Q in rotations])  # [1 + C]
    compared = (angles > AMBIGUOUS_DEGREES) & (amount >= MIN_STRUCTURE)  # [1 + C]; row 0 never
    if not compared.any():
        return None
    i = int(np.argmax(np.where(compared, precision, -np.inf)))
    if precision[i] < precision[0] - STRUCTURE_GAP:
        return None
    return (
        f"ambiguous: a pose {angles[i]:.0f} deg away fits what is not wall or floor at least as closely (close fit "
        f"{precision[i]:.2f} vs {precision[0]:.2f} of the source points off its dominant planes that each places near "
        "the target); the clouds may overlap in part"
    )


def off_plane_points(points: np.ndarray, unit: float, frame: CloudFrame | None = None) -> np.ndarray:
    """``[N]`` bool: the points of ``points [N, 3]`` farther than ``OFF_PLANE_DISTANCE`` times ``unit`` (an inlier
    distance) from each dominant plane of the cloud: along each axis of its :func:`service.plane_frames.plane_frame`,
    a slab two ``PLANE_SLAB`` bins wide across the axis holding at least ``PLANE_SHARE`` of the points among those
    whose normal lies along the axis (:func:`plane_offsets`). None where the cloud has no frame or no such plane.
    ``frame``: the cloud's :func:`service.plane_frames.cloud_frame` in the frame of ``points``, where the caller has
    it (the working source's, of its normalised copy: :attr:`Working.source_frame`)."""
    points = np.asarray(points, dtype=np.float64)
    frame = cloud_frame(points) if frame is None else frame
    if frame.axes is None:
        return np.zeros(len(points), dtype=bool)
    distance = np.full(len(points), np.inf)  # [N]: to the nearest dominant plane
    for axis in frame.axes.T:
        along = frame.defined & (np.abs(frame.normals @ axis) > np.cos(np.radians(AXIS_DEGREES)))  # [N]
        for offset in plane_offsets(points[along] @ axis, PLANE_SLAB * unit, PLANE_SHARE * len(points)):
            distance = np.minimum(distance, np.abs(points @ axis - offset))
    return np.isfinite(distance) & (distance > OFF_PLANE_DISTANCE * unit)


def plane_offsets(heights: np.ndarray, width: float, least: float) -> list[float]:
    """The offsets of the planes among ``heights [K]`` (points' positions along one axis): in bins ``width`` wide,
    the pairs of adjacent bins holding at least ``least`` points, most first, each apart from those taken before (not
    overlapping or touching them); each plane at the median height of its pair's points."""
    if len(heights) == 0:
        return []
    bins = np.floor((heights - heights.min()) / width).astype(np.int64)  # [K]
    counts = np.bincount(bins)  # [B]
    pairs = counts + np.r_[counts[1:], 0]  # [B]: bins b and b + 1 together
    taken = np.zeros(len(pairs), dtype=bool)  # [B]
    offsets = []
    for b in np.argsort(-pairs, kind="stable"):
        if pairs[b] < least:
            break
        if taken[max(b - 1, 0) : b + 3].any():
            continue
        taken[b : b + 2] = True
        offsets.append(float(np.median(heights[(bins == b) | (bins == b + 1)])))
    return offsets


def quarter_turns(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose ``R [3, 3], t [3]`` of ``points [N, 3]`` turned 90 deg either way about each principal axis of the
    moved points, through their centroid (the axes of :func:`service.stages.partial.half_turns`) -> ``R [6, 3, 3]``,
    ``t [6, 3]``."""
    centre, axes = principal_frame(points, R, t)  # [3], [3, 3] rows: principal axes
    turns = np.stack([rotation_of(sign * 0.5 * np.pi * axis, 0.5 * np.pi) for axis in axes for sign in (1.0, -1.0)])
    return turns @ R, (turns @ (t - centre)) + centre


def axis_turns(
    work: Working, R: np.ndarray, t: np.ndarray, surface: Surface | None = None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pose ``R [3, 3], t [3]`` turned by each of ``AXIS_TURN_DEGREES`` either way about the axis its least
    constrained motion turns about (:meth:`service.stability.Stability.turn_axis`, on the working clouds;
    ``surface``: the refinement's target surface, reused where it is the working target's); none where that motion
    is not mostly a turn (``ROTATION_SHARE``). The motion is measured at ``R, t`` itself: the final pose, which the
    fine stage may have moved from the pose whose ``stability`` the result reports."""
    moved = work.working_source @ R.T + t  # [Ns, 3]
    tree, working = work.working_target_lookup(surface)
    found = pose_stability(moved, work.tgt_w, tree, ICP_DISTANCE * work.norm.scale, working)
    axis = None if found is None or found.turn_share < ROTATION_SHARE else found.turn_axis()
    if axis is None:
        return []
    point, direction = axis  # [3], [3]
    angles = np.radians(AXIS_TURN_DEGREES)
    turns = [rotation_of(sign * angle * direction, angle) for angle in angles for sign in (1.0, -1.0)]  # [3, 3] each
    return [(Q @ R, Q @ (t - point) + point) for Q in turns]
