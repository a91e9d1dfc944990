"""Point-to-point ICP refinement of a ``src_to_tgt`` pose (numpy + scipy's cKDTree).

Each iteration moves the source with the current pose, pairs every moved point with its nearest
target point, keeps the pairs closer than ``max_distance`` and solves the increment with the
project's one weighted Procrustes (:func:`service.procrustes.weighted_procrustes`, uniform weights,
weighted centroid).  With that truncation the cost ``sum_i min(d_i^2, max_distance^2)`` never
increases from one iteration to the next.

With partial overlap, source points outside the overlap still find a (wrong) target point near the
edge of the overlap and pull the pose by a fraction of the point spacing (a few tenths of a degree
on 768-point partial views).  ``reciprocal=True`` (the default) keeps only mutual nearest
neighbours, which removes those pairs: two views sharing their points in the overlap then align
exactly.  It costs one more nearest-neighbour query per iteration, and the monotone-cost guarantee
above only holds for ``reciprocal=False`` (plain point-to-point ICP).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.procrustes import compose, weighted_procrustes

MIN_INLIERS = 3  # fewer pairs than this cannot fix a rigid pose: the pose is left as it is


@dataclass(frozen=True)
class IcpResult:
    """Refined ``src_to_tgt`` pose and how well it fits, measured at that pose."""

    rotation: np.ndarray  # [3, 3] float64, det +1
    translation: np.ndarray  # [3] float64, caller's units
    iterations: int  # Procrustes updates applied
    inlier_ratio: float  # fraction of source points with a target point closer than max_distance
    residual_rms: float  # RMS distance of those pairs (0 when there is none)


def icp(
    src: np.ndarray,
    tgt: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    max_distance: float,
    max_iterations: int = 30,
    tolerance: float = 1e-6,
    reciprocal: bool = True,
) -> IcpResult:
    """Refine ``(R0, t0)`` so that ``R src + t`` lies on ``tgt``.

    Args:
        src: ``(N, 3)`` source points.
        tgt: ``(M, 3)`` target points.
        R0: ``(3, 3)`` initial ``src_to_tgt`` rotation.
        t0: ``(3,)`` initial ``src_to_tgt`` translation.
        max_distance: pairs at this distance or farther are ignored (caller's units, > 0).
        max_iterations: most Procrustes updates.
        tolerance: stop once an update rotates by less than ``tolerance`` radians and translates by
            less than ``tolerance`` times the target's RMS radius.
        reciprocal: keep a pair only when the source point is also the target point's nearest
            source point (mutual nearest neighbours); ``False`` gives plain point-to-point ICP.

    Returns:
        :class:`IcpResult`; with fewer than ``MIN_INLIERS`` pairs the pose is not changed.  Its
        ``inlier_ratio`` and ``residual_rms`` use the distance rule only (as
        :func:`service.quality.assess` does), whatever ``reciprocal`` is.

    Raises:
        ValueError: on wrongly shaped inputs or a non-positive ``max_distance``.
    """
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    R = np.asarray(R0, dtype=np.float64)
    t = np.asarray(t0, dtype=np.float64)
    for name, array in (("src", src), ("tgt", tgt)):
        if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] == 0:
            raise ValueError(f"{name} must be (N, 3) with N >= 1, got {array.shape}")
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"R0 must be (3, 3) and t0 (3,), got {R.shape} and {t.shape}")
    if not max_distance > 0:
        raise ValueError(f"max_distance must be positive, got {max_distance}")
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be >= 0, got {max_iterations}")

    tree = cKDTree(tgt)
    src_tree = cKDTree(src) if reciprocal else None
    tgt_radius = float(np.sqrt(np.mean(np.sum((tgt - tgt.mean(axis=0)) ** 2, axis=1))))
    translation_tolerance = tolerance * max(tgt_radius, np.finfo(np.float64).tiny)
    iterations = 0
    for _ in range(max_iterations):
        src_in_tgt = src @ R.T + t  # [N, 3]
        dist, nearest = tree.query(src_in_tgt, k=1, distance_upper_bound=max_distance)  # [N], [N]
        inlier = dist < max_distance  # [N]; misses come back as inf
        if src_tree is not None:
            tgt_in_src = (tgt - t) @ R  # [M, 3] = R^T (tgt - t)
            nearest_src = src_tree.query(tgt_in_src, k=1)[1]  # [M]
            candidates = np.flatnonzero(inlier)
            inlier[candidates] = nearest_src[nearest[candidates]] == candidates
        if np.count_nonzero(inlier) < MIN_INLIERS:
            break
        R_step, t_step = weighted_procrustes(src_in_tgt[inlier], tgt[nearest[inlier]], None, "weighted")
        R, t = compose(R_step, t_step, R, t)
        iterations += 1
        angle = np.linalg.norm(R_step - np.eye(3)) / np.sqrt(2.0)  # ~ rotation angle when small
        if angle < tolerance and np.linalg.norm(t_step) < translation_tolerance:
            break

    src_in_tgt = src @ R.T + t  # [N, 3]
    dist, _ = tree.query(src_in_tgt, k=1, distance_upper_bound=max_distance)  # [N]
    inlier_dist = dist[dist < max_distance]
    residual_rms = float(np.sqrt(np.mean(inlier_dist**2))) if inlier_dist.size else 0.0
    return IcpResult(
        rotation=R,
        translation=t,
        iterations=iterations,
        inlier_ratio=float(inlier_dist.size / src.shape[0]),
        residual_rms=residual_rms,
    )
