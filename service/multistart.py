"""``refine="icp-plane-multistart"``: refine, then try the refined pose turned about each axis and keep the best.

Where the network's pose is 5-35 degrees off on a sparse or symmetric-looking cloud, point-to-plane ICP
settles in the wrong basin. This refinement turns the refined pose about the target's centroid by
``+-MULTISTART_ANGLES`` about x, y and z (12 starts plus the pose itself), moves each start with the
rotation search's short point-to-point ICP (:func:`service.icp.icp_many`), and keeps the start whose fit
is best by a **symmetric truncated point-to-plane** score: the mean distance of each cloud's points to
the other cloud's local tangent planes, both ways, each capped at ``MULTISTART_CAP`` (a point farther
than twice the cap from the other cloud counts the cap). Point-to-plane distances are not inflated by
the clouds' independent sampling as point-to-point ones are, and scoring both ways penalises poses that
fit one cloud into a part of the other. A start other than the pose itself then gets the precise
point-to-plane stage (``service.icp.icp_plane``; the wide stage of ``refine_plane`` pulled some back).

Measured on 300 sparse ModelNet40 pairs (384 / 384 points, bundled ``general`` 0.1.0): recall at (5 deg,
5 cm) 0.847 -> 0.867 through the service, at ~2.2x the time of ``icp-plane``; no change on dense pairs
(at ~2x); with ``general`` 0.2.0 0.867 -> 0.877. Picking among the same starts, this score reached
0.887 where the inlier ratio reached 0.860-0.867 and an oracle 0.947; most misses left are vases and
bottles, whose turn about their own axis no score can see (``docs/ACCURACY.md``, "Multi-start
refinement"; ``python -m bench.local_search``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from service.icp import IcpResult, Surface, icp_many, icp_plane, target_normals
from service.kdtree import KDTree

MULTISTART_ANGLES = (15.0, 30.0)  # degrees: the turns of the refined pose about x, y and z, both ways
MULTISTART_ICP_DISTANCE = 0.15  # normalised units: the short ICPs' correspondence cap (x the cloud scale)
MULTISTART_ICP_ITERATIONS = 20
MULTISTART_CAP = 0.05  # normalised units: a point's largest contribution to the fit score
# the short ICPs move every k-th source point so that about this many remain (fewer lost sparse pairs: 128 of
# 384 points gave recall 0.843 instead of 0.867; 256 of 768 dense points lost none)
MULTISTART_ICP_POINTS = 384


def turned_poses(R: np.ndarray, t: np.ndarray, centre: np.ndarray,
                 angles_deg: Sequence[float] = MULTISTART_ANGLES) -> tuple[np.ndarray, np.ndarray]:
    """``R [3, 3], t [3]`` and its turns by ``+-angle`` about x, y, z through ``centre`` -> ``[H, 3, 3], [H, 3]``
    (the pose itself first)."""
    turns = [np.eye(3)] + [
        Rotation.from_rotvec(np.radians(sign * angle) * axis).as_matrix()
        for angle in angles_deg
        for sign in (1.0, -1.0)
        for axis in np.eye(3)
    ]
    D = np.stack(turns)  # [H, 3, 3]
    return D @ R, (D @ (t - centre)[:, None])[..., 0] + centre


def plane_distances(points: np.ndarray, tree: KDTree, cloud: np.ndarray,
                    normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-point and point-to-plane distances ``[N]`` of ``points`` to ``cloud`` (with ``normals``)."""
    dist, idx = tree.query(points)
    return dist, np.abs(((points - cloud[idx]) * normals[idx]).sum(1))


def symmetric_plane_scores(
    src: np.ndarray, tgt: np.ndarray, R: np.ndarray, t: np.ndarray, cap: float, target_surface: Surface | None = None
) -> np.ndarray:
    """Fit score ``[H]`` (lower is better) of each pose ``R [H, 3, 3]``, ``t [H, 3]`` of ``src`` onto ``tgt``:
    mean capped point-to-plane distance of ``src`` to ``tgt`` plus that of ``tgt`` to the moved ``src``.
    ``target_surface``: ``Surface.of(tgt)`` when the caller has it."""
    surface = Surface.of(tgt) if target_surface is None else target_surface
    tgt_tree, tgt_normals, src_normals = surface.tree, surface.normals, target_normals(src)[0]
    scores = np.empty(len(R))
    for h, (R_h, t_h) in enumerate(zip(R, t, strict=True)):
        moved = src @ R_h.T + t_h  # [N, 3]
        dist, plane = plane_distances(moved, tgt_tree, tgt, tgt_normals)
        dist_back, plane_back = plane_distances(tgt, KDTree(moved), moved, src_normals @ R_h.T)
        scores[h] = (
            np.minimum(np.where(dist < 2 * cap, plane, cap), cap).mean()
            + np.minimum(np.where(dist_back < 2 * cap, plane_back, cap), cap).mean()
        )
    return scores


def best_turned_pose(
    src: np.ndarray, tgt: np.ndarray, R: np.ndarray, t: np.ndarray, scale: float, target_surface: Surface | None = None
) -> tuple[np.ndarray, np.ndarray, int]:
    """The best of ``R, t`` and its turns after short ICPs (the module docstring) -> ``R [3, 3], t [3]`` and
    the index of the winning start (0: the pose itself). ``scale``: the clouds' size in normalised units;
    ``target_surface``: ``Surface.of(tgt)`` when the caller has it."""
    R_h, t_h = turned_poses(R, t, tgt.mean(axis=0))
    stride = max(1, len(src) // MULTISTART_ICP_POINTS)
    R_h, t_h = icp_many(
        src[::stride], tgt, R_h, t_h, max_distance=MULTISTART_ICP_DISTANCE * scale,
        max_iterations=MULTISTART_ICP_ITERATIONS,
    )
    best = int(np.argmin(symmetric_plane_scores(src, tgt, R_h, t_h, MULTISTART_CAP * scale, target_surface)))
    return (R, t, 0) if best == 0 else (R_h[best], t_h[best], best)  # the pose itself as refined, not re-moved


def multistart(src: np.ndarray, tgt: np.ndarray, refined: IcpResult, scale: float, distance: float,
               max_iterations: int, target_surface: Surface | None = None) -> IcpResult:
    """The multistart stage of ``refine="icp-plane-multistart"``: ``refined`` (a refinement of ``src`` onto
    ``tgt``), or, when a turned start fits better (:func:`best_turned_pose`), that start moved by the precise
    point-to-plane stage only (the wide one could pull it back). ``distance``: its correspondence cap."""
    R_turn, t_turn, start = best_turned_pose(src, tgt, refined.rotation, refined.translation, scale, target_surface)
    if not start:
        return refined
    return icp_plane(src, tgt, R_turn, t_turn, max_distance=distance, max_iterations=max_iterations,
                     target_surface=target_surface)
