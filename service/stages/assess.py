"""Stage 6, assess: quality and stability of the final pose on the working clouds -> the result."""

from __future__ import annotations

import time

import numpy as np

from service.kdtree import KDTree
from service.network_loop import NetworkOutput
from service.quality import assess
from service.result import IterationPose, RegistrationResult
from service.rotation_search import SearchCandidate
from service.stability import pose_stability, weak_motion_warning
from service.stages.network import Candidates
from service.stages.normalise import ICP_DISTANCE, Working, to_caller
from service.stages.refine import Refined


def iteration_poses(work: Working, candidate: SearchCandidate) -> list[IterationPose]:
    """The caller's cumulative pose after each network iteration of ``candidate`` (from its start rotation)."""
    net, R_start = candidate.output, candidate.start
    return [IterationPose(*to_caller(work, R @ R_start, t)) for R, t in net.cumulative]


def svd_weights(net: NetworkOutput) -> np.ndarray:
    """``[K]`` float32: the network's SVD weights summing to ~1 (uniform when all are zero)."""
    weights = net.weights
    w_sum = weights.sum()
    return (weights / (w_sum + 1e-8) if w_sum > 0 else np.full_like(weights, 1 / len(weights))).astype(np.float32)


def assess_result(work: Working, found: Candidates, refined: Refined, iterations: int, return_iterations: bool,
                  timing: dict[str, float]) -> RegistrationResult:
    """Inlier ratio, residual and ``reliable`` (:func:`service.quality.assess`), the pose's stability
    (:func:`service.stability.pose_stability`) and the winning candidate's correspondences as a result.

    Not reliable when the quality says so, the candidate ranking was ambiguous, or the motion is weakly
    constrained; records ``timing["postprocess"]``."""
    candidate = found.poses[refined.pick]
    net = candidate.output
    poses = iteration_poses(work, candidate) if return_iterations else []
    t4 = time.perf_counter()
    R, t, surface, tgt_w = refined.rotation, refined.translation, refined.surface, work.tgt_w
    working = surface if surface is not None and work.tgt_r is tgt_w else None  # the working target's normals
    tree = KDTree(tgt_w) if working is None else working.tree  # shared by the two checks below
    src = work.src[work.idx_s]  # [Ns, 3] working source, caller's frame
    quality = assess(src, tgt_w, R, t, work.inlier_distance, tree)
    stability = pose_stability(src @ R.T + t, tgt_w, tree, ICP_DISTANCE * work.norm.scale, working)
    weak = weak_motion_warning(stability)
    result = RegistrationResult(
        rotation=R,
        translation=t,
        source_index=found.net_s[net.src_kp].astype(np.int64),
        target_index=found.net_t[net.tgt_kp[net.matched]].astype(np.int64),
        credibility=net.credibility.astype(np.float32),
        weight=svd_weights(net),
        inlier_ratio=quality.inlier_ratio,
        residual_rms=quality.residual_rms,
        reliable=bool(quality.reliable) and refined.ambiguity is None and weak is None,  # assess(): degenerate
        warnings=[*quality.warnings, *refined.warnings, *(w for w in (refined.ambiguity, weak) if w)],
        stability=None if stability is None else stability.eigenvalue,
        iterations=iterations,
        timing_ms=timing,
        iteration_poses=poses,
    )
    timing["postprocess"] = 1000 * (time.perf_counter() - t4)
    return result
