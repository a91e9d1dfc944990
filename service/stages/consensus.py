"""Stage 6b, consensus: a result that is not ``reliable`` against the pose the clouds' descriptors agree on.

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
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING

import numpy as np

from service.icp import icp_plane
from service.options import RegistrationOptions
from service.procrustes import compose
from service.refine_modes import PLANE_MODES
from service.result import RegistrationResult
from service.stages.assess import assess_result
from service.stages.features import dense_enough_to_describe, feature_candidate
from service.stages.network import Candidates
from service.stages.normalise import Working
from service.stages.refine import Refined

if TYPE_CHECKING:
    from service.registrar import Registrar

# The feature pose replaces a result only where at least this many matched pairs agree with it: on the real-scan
# set's room pairs wrong feature poses had at most 15 (decisions/0051), right ones on room crops 17-64.
CONSENSUS_SUPPORT = 16
# ... and the result keeps less than this share of them: wrong results that a right feature pose replaced kept
# 0.00-0.48 of its support, right results 0.59-1.0 but three, each replaced by a right pose or `reliable`
# (decisions/0085).
CONSENSUS_SHARE = 0.5
CONSENSUS_ITERATIONS = 30  # point-to-plane updates from the feature pose (it lies up to about 0.3 m off on rooms)
CONSENSUS_TOLERANCE = 1e-5  # as the fine stage's
DESCRIPTOR_CONSENSUS = "descriptor consensus"  # first words of the note on a result this stage gave


def consensus_note(support: int, kept: int) -> str:
    """The note on a result the descriptors' consensus gave: ``support`` matched pairs agree with it, ``kept`` with the
    result it replaced."""
    return (f"{DESCRIPTOR_CONSENSUS}: {support} matched surface patches agree with this pose, {kept} with the pose the "
            "refinement ranked first; this one is returned")


def after_guess(work: Working, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The caller's pose ``R [3, 3], t [3]`` as a pose of the source moved by the initial guess (the frame of the
    feature pose and of the candidates): the inverse of composing with the guess."""
    moved = R @ work.R_init.T  # [3, 3]
    return moved, t - moved @ work.t_init


def applies(work: Working, result: RegistrationResult, options: RegistrationOptions) -> bool:
    """Whether the consensus stage looks at ``result``: it is not ``reliable``, the refinement is point to plane (the
    fine clouds' normals), and both entered clouds are dense enough to describe."""
    return (not result.reliable and options.refine_mode in PLANE_MODES and options.refine_points is None
            and dense_enough_to_describe(work))


def consensus(registrar: Registrar, work: Working, result: RegistrationResult, options: RegistrationOptions,
              iterations: int, keypoints: int, timing: dict[str, float]) -> RegistrationResult:
    """``result`` (caller's frames of the anchored clouds), or where :func:`applies` and the descriptors' consensus
    outweighs it, the feature pose refined on the fine clouds and assessed (:func:`service.stages.assess.assess_result`)
    with a note naming both supports; records ``timing["consensus"]`` where it computed descriptors."""
    if not applies(work, result, options):
        return result
    started = time.perf_counter()
    try:
        pose = work.feature_pose  # of the source moved by the initial guess (the feature candidate's, where it ran)
        if pose is None or pose.support < CONSENSUS_SUPPORT:
            return result
        kept = pose.support_of(*after_guess(work, result.rotation, result.translation))
        if kept >= CONSENSUS_SHARE * pose.support:
            return result
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
        return dataclasses.replace(agreed, warnings=[*agreed.warnings, consensus_note(pose.support, kept)],
                                   timing_ms=timing)
    finally:
        timing["consensus"] = 1000 * (time.perf_counter() - started)
