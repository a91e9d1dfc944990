"""Stage 6, assess: quality and stability of the final pose on the working clouds -> the result."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from service.network_loop import NetworkOutput
from service.quality import LOOSE_FIT, NEAR_SURFACE_FACTOR, ReverseFit, assess, near_surface_share, reverse_fit
from service.quality import poor_fit as poor_fit_of  # the rule's band, given the attainable ratio
from service.result import IterationPose, RegistrationResult
from service.rotation_search import SearchCandidate
from service.stability import ROTATION_SHARE, WEAK_EIGENVALUE, Stability, pose_stability, weak_motion_warning
from service.stages.network import Candidates
from service.stages.normalise import ICP_DISTANCE, Working, to_caller
from service.stages.ranking import plane_frames_on_the_surface, samples_the_surface
from service.stages.refine import Refined

# With a dense target (service.stages.ranking.samples_the_surface), of the moved working source points within
# NEAR_SURFACE_FACTOR inlier distances of the entered target's points a reliable result has at least this share
# within one (docs/decisions/0015-reliable-on-the-target-surface.md).
RELIABLE_SURFACE_SHARE = 0.66
# With a dense target, a pose whose stability is below this is weakly constrained (not reliable), instead of
# service.stability.WEAK_EIGENVALUE: right poses on real scans stay at 0.03 and above, cut or not, while a wrong pose
# on a small patch of the overlap turns or slides more freely (docs/decisions/0050-a-firmer-pose-on-dense-targets.md).
# Only where the least constrained motion is not mostly a turn (turns_at_the_common_floor).
RELIABLE_STABILITY_ON_SURFACE = 0.02


def off_the_surface(work: Working, R: np.ndarray, t: np.ndarray) -> str | None:
    """A ``loose fit`` warning when the entered target is dense and the pose ``R, t`` (caller's units) leaves too many
    of the working source points near its surface off it (below ``RELIABLE_SURFACE_SHARE``; the working target's own
    tight-fit test, :func:`service.quality.assess`, measures to 768 samples only), else ``None``."""
    if not samples_the_surface(work):
        return None
    share = near_surface_share(work.working_source, work.tgt_e, R, t, work.inlier_distance, work.entered_target_tree)
    if share >= RELIABLE_SURFACE_SHARE:
        return None
    return (
        f"{LOOSE_FIT}: of the source points within {NEAR_SURFACE_FACTOR:g} inlier distances of the target's points "
        f"only {share:.3f} lie within one, < {RELIABLE_SURFACE_SHARE}; a right pose lies on the target's surface "
        "where they overlap"
    )


def reliable_attainable(work: Working) -> tuple[float, bool]:
    """What the ``reliable`` rule judges the inlier ratio against, and whether it is the surface estimate: on a dense
    entered target (:func:`service.stages.ranking.samples_the_surface`), the ratio a right pose reaches on its surface
    (:attr:`Working.surface_attainable_ratio`, judged with :func:`service.quality.assess`'s on-surface factors);
    elsewhere what the working target's density allows (:attr:`Working.attainable_ratio`, with that estimate's)."""
    if samples_the_surface(work):
        return work.surface_attainable_ratio, True
    return work.attainable_ratio, False


def poor_fit(work: Working, inlier_ratio: float) -> bool:
    """Whether ``inlier_ratio`` is the ``reliable`` rule's "poor fit" on ``work`` (:func:`service.quality.poor_fit`
    against :func:`reliable_attainable`)."""
    return poor_fit_of(inlier_ratio, *reliable_attainable(work))


def reverse_fit_on(work: Working, R: np.ndarray, t: np.ndarray) -> Callable[[], ReverseFit] | None:
    """Where the entered target samples its surface densely (:func:`service.stages.ranking.samples_the_surface`) and
    the clouds are not rooms (:func:`service.stages.ranking.plane_frames_on_the_surface`), the pose ``R, t``'s
    :func:`service.quality.reverse_fit` of the working target against the working source, for
    :func:`service.quality.assess` to ask where the inlier ratio alone keeps the result from ``reliable``; else
    ``None``. Sparse targets and rooms keep the source-side rule: there wrong poses (half-turned partial views, a
    room turned onto its walls) explain a cut target as well as right ones
    (``docs/decisions/0084-a-cut-target-the-source-explains.md``)."""
    if not samples_the_surface(work) or plane_frames_on_the_surface(work):
        return None
    return lambda: reverse_fit(work.working_source, work.tgt_w, R, t, work.inlier_distance,
                               work.source_attainable_ratio)  # the source's ratio measured only where asked


def weak_below(work: Working) -> float:
    """The stability eigenvalue below which a pose on ``work`` is weakly constrained: ``RELIABLE_STABILITY_ON_SURFACE``
    on a dense entered target (:func:`service.stages.ranking.samples_the_surface`), else ``WEAK_EIGENVALUE``."""
    return RELIABLE_STABILITY_ON_SURFACE if samples_the_surface(work) else WEAK_EIGENVALUE


def turns_at_the_common_floor(stability: Stability | None) -> Stability | None:
    """``stability`` judged at ``WEAK_EIGENVALUE`` where its least constrained motion is mostly a turn
    (``ROTATION_SHARE``) and a dense target's ``RELIABLE_STABILITY_ON_SURFACE`` was asked: the symmetry check turns such
    a result about that motion's axis (stability below ``service.stages.symmetry.AXIS_TURN_STABILITY``) and compares
    the fits, which tests a free turn itself, while right turntable scans of smooth objects (cars, a person, round
    blobs) hold turns at 0.011-0.019. A slide keeps the firmer floor: the symmetry check does not move a pose along one,
    and the wrong result the floor was chosen on slid (``docs/decisions/0050-a-firmer-pose-on-dense-targets.md``)."""
    if stability is None or stability.weak_below <= WEAK_EIGENVALUE or stability.turn_share < ROTATION_SHARE:
        return stability
    return dataclasses.replace(stability, weak_below=WEAK_EIGENVALUE)


def iteration_poses(work: Working, candidate: SearchCandidate) -> list[IterationPose]:
    """The caller's cumulative pose after each network iteration of ``candidate`` (from its start rotation)."""
    net, R_start = candidate.output, candidate.start
    return [IterationPose(*to_caller(work, R @ R_start, t)) for R, t in net.cumulative]


def svd_weights(net: NetworkOutput) -> np.ndarray:
    """``[K]`` float32: the network's SVD weights summing to ~1 (uniform when all are zero)."""
    weights = net.weights
    w_sum = weights.sum()
    return (weights / (w_sum + 1e-8) if w_sum > 0 else np.full_like(weights, 1 / len(weights))).astype(np.float32)


def assess_result(
    work: Working,
    found: Candidates,
    refined: Refined,
    iterations: int,
    return_iterations: bool,
    timing: dict[str, float],
    unrefined: bool = False,
) -> RegistrationResult:
    """Inlier ratio, residual and ``reliable`` (:func:`service.quality.assess`; ``unrefined``: the pose is the
    network's, ``refine="none"``), the pose's stability (:func:`service.stability.pose_stability`) and the winning
    candidate's correspondences as a result.

    Not reliable when the quality says so, the candidate ranking was ambiguous, the motion is weakly constrained
    (:func:`weak_below`), or the pose lies off a dense target's surface (:func:`off_the_surface`); records
    ``timing["postprocess"]``."""
    candidate = found.poses[refined.pick]
    net = candidate.output
    poses = iteration_poses(work, candidate) if return_iterations else []
    t4 = time.perf_counter()
    R, t, surface, tgt_w = refined.rotation, refined.translation, refined.surface, work.tgt_w
    tree, working = work.working_target_lookup(surface)  # shared by the two checks below
    src = work.working_source  # [Ns, 3] caller's frame
    attainable, on_surface = reliable_attainable(work)
    quality = assess(src, tgt_w, R, t, work.inlier_distance, tree, attainable, on_surface, reverse_fit_on(work, R, t),
                     unrefined)
    stability = pose_stability(src @ R.T + t, tgt_w, tree, ICP_DISTANCE * work.norm.scale, working, weak_below(work))
    weak = weak_motion_warning(turns_at_the_common_floor(stability))
    reliable = bool(quality.reliable) and refined.ambiguity is None and weak is None  # assess(): degenerate
    loose = off_the_surface(work, R, t) if reliable else None  # only where nothing else took `reliable` away
    result = RegistrationResult(
        rotation=R,
        translation=t,
        source_index=found.net_s[net.src_kp].astype(np.int64),
        target_index=found.net_t[net.tgt_kp[net.matched]].astype(np.int64),
        credibility=net.credibility.astype(np.float32),
        weight=svd_weights(net),
        inlier_ratio=quality.inlier_ratio,
        residual_rms=quality.residual_rms,
        reliable=reliable and loose is None,
        warnings=[*quality.warnings, *refined.warnings, *(w for w in (refined.ambiguity, weak, loose) if w)],
        stability=None if stability is None else stability.eigenvalue,
        iterations=iterations,
        timing_ms=timing,
        iteration_poses=poses,
    )
    timing["postprocess"] = 1000 * (time.perf_counter() - t4)
    return result
