"""Stage 6b, consensus: a doubtful result against the pose the clouds' descriptors agree on.

The refinement and the candidates' ranking judge a pose by how much of the source it lays on the target. Where two
scans overlap by a third or less, a wrong pose can lay more of it there than the right one (a room turned onto its
walls and floor, a slide along them), and the pipeline returns it. Local descriptors judge differently: the right pose
brings dozens of matched surface patches together, a wrong one a few. Where a result is not ``reliable`` and both
clouds are dense enough to describe (:func:`service.stages.features.dense_enough_to_describe`), this stage computes
the feature pose of the entered clouds (:func:`service.feature_match.feature_pose`) and counts how many of its matched
pairs agree with the result. Where at least ``CONSENSUS_SUPPORT`` agree with the feature pose and the result keeps
less than ``CONSENSUS_SHARE`` of that, the feature pose refined on the fine clouds (point-to-plane ICP at one inlier
distance, as :mod:`service.stages.fine` pairs them) replaces it, assessed as any result is
(``docs/decisions/0085-a-descriptor-consensus-for-doubtful-results.md``).

A ``reliable`` result is looked at too where both clouds are built of orthogonal planes
(:func:`service.stages.ranking.plane_frames_on_the_surface`: rooms, LiDAR frames) and it overlays less than
``PARTIAL_OVERLAY`` of what a right pose reaches on the target's surface: of two views that overlap in part, a room
turned onto its walls or slid along them can pass every check. It is replaced only where it keeps less than
``RELIABLE_CONSENSUS_SHARE`` (``docs/decisions/0086-the-consensus-looks-at-reliable-rooms.md``), or less than
``ONE_PLACE_SHARE`` where the feature pose is one strong place (:func:`one_strong_place`: at least ``STRONG_SUPPORT``
agreeing pairs and no other place with ``ONE_PLACE_RIVAL`` of them;
``0092-a-reliable-room-gives-way-to-one-strong-place.md``).

Where the result it returns (kept or replaced) is a room's whose only doubts are ones the descriptors settle
(``ROOM_DOUBTS``: a poor fit, weak constraint, another place that fits almost as well), at least
``CONFIRMING_SUPPORT`` matched pairs agree with it and it lies on the target's surface, it is ``reliable``, its
warnings kept and a note added: two room views that overlap by a third lay a third of the source on the target, below
the rule's share of what a right pose reaches, however right the pose, and flat walls and floors let a right pose
slide with little change of fit; matched patches that agree within two voxels place it all the same
(``docs/decisions/0087-descriptors-confirm-rooms-that-overlap-in-part.md``,
``0089-descriptors-settle-what-the-fit-cannot-place.md``). Over other clouds a weak turn is settled (an object
nearly round about an axis), where the result keeps ``OBJECT_CONFIRMING_SHARE`` of the feature pose's support
(``0090-descriptors-settle-a-round-objects-turn.md``); where the stage put the feature pose in the result's place,
that pose must also be the only place the descriptors point to: no other reaches ``UNIQUE_SHARE`` of its support
(``0091-a-replaced-round-objects-turn-needs-one-place.md``). Where the feature pose is that one place, a weak slide
and, where the clouds are not two range images (free space settles theirs where it is the only doubt), a loose fit of
the working target are settled too (``ONE_PLACE_OBJECT_DOUBTS``, ``0093-one-place-settles-an-objects-slide.md``).
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING

import numpy as np

from service.feature_match import FeaturePose
from service.icp import icp_plane
from service.options import RegistrationOptions
from service.procrustes import compose
from service.quality import POOR_FIT, WORKING_LOOSE_FIT
from service.refine_modes import PLANE_MODES
from service.result import RegistrationResult
from service.stability import WEAK_SLIDE, WEAK_TURN, WEAKLY_CONSTRAINED
from service.stages.assess import assess_result, off_the_surface
from service.stages.features import dense_enough_to_describe, feature_candidate
from service.stages.network import Candidates
from service.stages.normalise import Working
from service.stages.ranking import SHIFT_AMBIGUITY, plane_frames_on_the_surface
from service.stages.refine import Refined
from service.stages.withdraw import CONFIRMED_BY_DESCRIPTORS  # the note on a result it made `reliable`

if TYPE_CHECKING:
    from service.registrar import Registrar

# The feature pose replaces a result only where at least this many matched pairs agree with it: on the real-scan
# set's room pairs wrong feature poses had at most 15 (decisions/0051), right ones on room crops 17-64.
CONSENSUS_SUPPORT = 16
# ... and the result keeps less than this share of them: wrong results that a right feature pose replaced kept
# 0.00-0.48 of its support, right results 0.59-1.0 but three, each replaced by a right pose or `reliable`
# (decisions/0085).
CONSENSUS_SHARE = 0.5
# ... or, for a `reliable` room result, this share: wrong ones kept 0.00-0.48, 10 of 13 below 0.3, and right lamp scans
# that pass as built of orthogonal planes kept 0.38-0.45 of a wrong feature pose's support (decisions/0086).
RELIABLE_CONSENSUS_SHARE = 0.3
# ... or this share where the feature pose is one strong place: at least STRONG_SUPPORT matched pairs agree with it and
# no other place the descriptors point to (FeaturePose.rival) has ONE_PLACE_RIVAL of them. Of 719 `reliable` rooms
# looked at (room crops, synthetic rooms, LiDAR variants, the set's rooms), 516 had such a feature pose, none over
# 10 deg off; the right results kept 0.865 of its support or more but two (0.18, replaced under 0.3 already; 0.30,
# 9.7 deg off), three wrong ones 0.52-0.73 (decisions/0092).
ONE_PLACE_SHARE = 0.8
STRONG_SUPPORT = 60
ONE_PLACE_RIVAL = 0.3
# A `reliable` room result is looked at only where its inlier ratio is below this share of what a right pose reaches
# on the target's surface (the views overlap in part): wrong ones reached 0.51-0.82 of it, right ones on synthetic
# rooms and LiDAR frames 0.85-1.03, on the set's and cropped room fragments 0.50-0.77 (decisions/0086).
PARTIAL_OVERLAY = 0.9
# A room result whose only doubts are ROOM_DOUBTS is `reliable` where at least this many matched pairs agree with
# it and it lies on the target's surface: wrong room results with a poor fit kept at most 25 agreeing pairs (the set's
# fragments, room crops, synthetic rooms), right ones at 30% overlap 17-74 (decisions/0087); wrong ones weakly
# constrained or with another place that fits kept at most 13, right ones 17-131 (decisions/0089).
CONFIRMING_SUPPORT = 30
# The doubts matched pairs settle (first words of the warnings): too little of the source on the target, a slide or
# turn that hardly changes the fit, another place that fits almost as well. Not a turn that fits as well (the symmetry
# check's and the ranking's `ambiguous: a pose N deg away`: wrong quarter turns of synthetic rooms kept 31 agreeing
# pairs), a low overlap or a loose fit (decisions/0089).
ROOM_DOUBTS = (POOR_FIT, WEAKLY_CONSTRAINED, SHIFT_AMBIGUITY)
# Over clouds that are not rooms a weak turn is settled (an object turned about an axis with little change of fit: a
# vase, a cup, a lumpy sphere; the symmetry check turns a confirmed pose again), a poor fit never (a derived dragon
# pair 9.8 deg off kept all of its 34 pairs) (decisions/0090); a weak slide and a loose fit in one place only (below).
OBJECT_DOUBTS = (WEAK_TURN,)
# ... where the result also keeps at least this share of the feature pose's support: on simulated turntable scans
# wrong results the stage kept with at least 30 agreeing pairs kept at most 0.80 of it, 93 of the 108 right ones 0.9 or
# more (decisions/0090).
OBJECT_CONFIRMING_SHARE = 0.9
# ... and where the stage put the feature pose in the result's place, no other place the descriptors point to
# (FeaturePose.rival) reaches this share of its support: of the feature poses of objects with at least 30 agreeing pairs
# on the choosing sets 18 of 634 lay over 10 deg off, 3 of the 550 below this share (decisions/0091).
UNIQUE_SHARE = 0.6
# ... and where the feature pose is one place in that sense (kept or replaced), a slide that hardly changes the fit and
# a loose fit of the working target (not the entered target's, which confirmed() asks of every result), the latter
# only where the clouds are not two range images (free space, which runs before, settles theirs where it is the only
# doubt, and declines it above 0.03 of a scan in free space, 0.01 on a coarser view, or where it saw under 0.1 of a
# scan; decisions/0094, 0096): on the choosing sets 48 of 50 object results with such doubts
# alone were right, the 2 wrong ones kept 16 and 13 pairs; 30 right ones passed the rule. A poor fit stays unsettled:
# none passed it (decisions/0093).
ONE_PLACE_OBJECT_DOUBTS = (WEAK_SLIDE, WORKING_LOOSE_FIT)
CONSENSUS_ITERATIONS = 30  # point-to-plane updates from the feature pose (it lies up to about 0.3 m off on rooms)
CONSENSUS_TOLERANCE = 1e-5  # stop on updates below this (rad, x RMS radius)
DESCRIPTOR_CONSENSUS = "descriptor consensus"  # first words of the note on a result this stage gave


def consensus_note(support: int, kept: int) -> str:
    """The note on a result the descriptors' consensus gave: ``support`` matched pairs agree with it, ``kept`` with the
    result it replaced."""
    return (f"{DESCRIPTOR_CONSENSUS}: {support} matched surface patches agree with this pose, {kept} with the pose the "
            "refinement ranked first; this one is returned")


def confirmed_note(support: int) -> str:
    """The note on a result the descriptors confirm: ``support`` matched pairs agree with it."""
    return (f"{CONFIRMED_BY_DESCRIPTORS}: {support} matched surface patches agree with this pose (at least "
            f"{CONFIRMING_SUPPORT}); they place the source where the fit alone cannot")


def settled_by_descriptors(result: RegistrationResult, doubts: tuple[str, ...] = ROOM_DOUBTS) -> bool:
    """Whether every doubt of ``result`` (at least one; the consensus note is none) is one of ``doubts`` (first
    words of warnings)."""
    raised = [w for w in result.warnings if not w.startswith(DESCRIPTOR_CONSENSUS)]
    return bool(raised) and all(w.startswith(doubts) for w in raised)


def confirmed(work: Working, result: RegistrationResult, support: int, pose: FeaturePose, replaced: bool
              ) -> RegistrationResult:
    """``result``, ``reliable`` with a note where ``support`` (the matched pairs that agree with it) reaches
    ``CONFIRMING_SUPPORT``, the descriptors settle its doubts and it lies on the target's surface where they overlap
    (:func:`service.stages.assess.off_the_surface`, which the rule asks only of results that pass the ratio check).
    They settle a room's (both clouds built of orthogonal planes) ``ROOM_DOUBTS``, kept or ``replaced``; over other
    clouds ``OBJECT_DOUBTS`` and ``ONE_PLACE_OBJECT_DOUBTS`` (not a loose fit between range images:
    :func:`loose_between_range_images`), where ``support`` is at least ``OBJECT_CONFIRMING_SHARE`` of the feature
    ``pose``'s and, for a result ``replaced`` by that pose or with one of ``ONE_PLACE_OBJECT_DOUBTS``, no other place
    the descriptors point to reaches ``UNIQUE_SHARE`` of it (:meth:`service.feature_match.FeaturePose.rival`)."""
    if result.reliable or support < CONFIRMING_SUPPORT:
        return result
    room = plane_frames_on_the_surface(work)
    if not settled_by_descriptors(result, ROOM_DOUBTS if room else OBJECT_DOUBTS + ONE_PLACE_OBJECT_DOUBTS):
        return result
    if not room and loose_between_range_images(work, result):
        return result
    if not room and support < OBJECT_CONFIRMING_SHARE * pose.support:
        return result
    if off_the_surface(work, result.rotation, result.translation):
        return result
    needs_one_place = replaced or any(w.startswith(ONE_PLACE_OBJECT_DOUBTS) for w in result.warnings)
    if not room and needs_one_place and pose.has_rival(UNIQUE_SHARE):
        return result
    return dataclasses.replace(result, reliable=True, warnings=[*result.warnings, confirmed_note(support)])


def loose_between_range_images(work: Working, result: RegistrationResult) -> bool:
    """Whether ``result`` fits the working target loosely and both clouds are range images, as free space reads them
    for a confirmation (:attr:`Working.confirming_views`): such a loose fit is free space's to settle
    (:mod:`service.stages.free_space`, where it is the result's only doubt), not the descriptors'; beside one range
    image alone free space confirms nothing (``docs/decisions/0096``). The views are built only where the warning is
    there."""
    loose = any(w.startswith(WORKING_LOOSE_FIT) for w in result.warnings)
    return loose and None not in work.confirming_views


def after_guess(work: Working, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The caller's pose ``R [3, 3], t [3]`` as a pose of the source moved by the initial guess (the frame of the
    feature pose and of the candidates): the inverse of composing with the guess."""
    moved = R @ work.R_init.T  # [3, 3]
    return moved, t - moved @ work.t_init


def share_to_keep(work: Working, result: RegistrationResult, options: RegistrationOptions) -> float | None:
    """The share of the feature pose's support ``result`` must keep, or None where the stage does not look at it: the
    refinement is point to plane (the fine clouds' normals), both entered clouds are dense enough to describe, and the
    result is not ``reliable`` (``CONSENSUS_SHARE``) or is a room's that overlays its source in part
    (``RELIABLE_CONSENSUS_SHARE``)."""
    if options.refine_mode not in PLANE_MODES or not work.refines_on_working_clouds:
        return None
    if not dense_enough_to_describe(work):
        return None
    if not result.reliable:
        return CONSENSUS_SHARE
    in_part = plane_frames_on_the_surface(work) and (
        result.inlier_ratio < PARTIAL_OVERLAY * work.surface_attainable_ratio)
    return RELIABLE_CONSENSUS_SHARE if in_part else None


def one_strong_place(pose: FeaturePose) -> bool:
    """Whether at least ``STRONG_SUPPORT`` matched pairs agree with ``pose`` and no other place the descriptors point
    to (:meth:`service.feature_match.FeaturePose.rival`) has ``ONE_PLACE_RIVAL`` of them."""
    return pose.support >= STRONG_SUPPORT and not pose.has_rival(ONE_PLACE_RIVAL)


def gives_way(result: RegistrationResult, pose: FeaturePose, kept: int, share: float) -> bool:
    """Whether ``result``, with which ``kept`` of the feature ``pose``'s matched pairs agree, gives way to that pose:
    it keeps less than ``share`` of its support, or it is ``reliable`` (a room the stage looks at) and keeps less than
    ``ONE_PLACE_SHARE`` of a pose that is :func:`one_strong_place` (its rival computed only then)."""
    if kept < share * pose.support:
        return True
    return result.reliable and kept < ONE_PLACE_SHARE * pose.support and one_strong_place(pose)


def consensus(registrar: Registrar, work: Working, result: RegistrationResult, options: RegistrationOptions,
              iterations: int, keypoints: int, timing: dict[str, float]) -> RegistrationResult:
    """``result`` (caller's frames of the anchored clouds), or where it :func:`gives_way` to the descriptors'
    consensus (keeps less than :func:`share_to_keep` of it, or a ``reliable`` room less than ``ONE_PLACE_SHARE`` of one
    strong place), the feature pose refined on the fine clouds and assessed
    (:func:`service.stages.assess.assess_result`) with a note naming both supports; either :func:`confirmed` by the
    pairs that agree with it. Records ``timing["consensus"]`` where it looked."""
    share = share_to_keep(work, result, options)
    if share is None:
        return result
    started = time.perf_counter()
    try:
        pose = work.feature_pose  # of the source moved by the initial guess (the feature candidate's, where it ran)
        if pose is None or pose.support < CONSENSUS_SUPPORT:
            return result
        kept = pose.support_of(*after_guess(work, result.rotation, result.translation))
        if not gives_way(result, pose, kept, share):
            return confirmed(work, result, kept, pose, replaced=False)
        start = compose(pose.rotation, pose.translation, work.R_init, work.t_init)  # the caller's pose
        fitted = icp_plane(work.fine_source, work.fine_target, *start,
                           max_distance=work.inlier_distance, max_iterations=CONSENSUS_ITERATIONS,
                           tolerance=CONSENSUS_TOLERANCE, target_surface=work.fine_target_surface)
        if fitted.warnings:
            return result
        candidate = feature_candidate(registrar, work, *after_guess(work, fitted.rotation, fitted.translation),
                                      iterations, keypoints, timing, "consensus")
        refined = Refined(fitted.rotation, fitted.translation, 0, (), None, None)
        assess_timing = dict(timing)
        agreed = assess_result(work, Candidates([candidate], work.idx_s, work.idx_t), refined, result.iterations,
                               options.return_iterations, assess_timing)
        agreed = dataclasses.replace(agreed, warnings=[*agreed.warnings, consensus_note(pose.support, kept)],
                                     timing_ms=timing)
        return confirmed(work, agreed, pose.support_of(*after_guess(work, fitted.rotation, fitted.translation)), pose,
                         replaced=True)
    finally:
        timing["consensus"] = 1000 * (time.perf_counter() - started)
