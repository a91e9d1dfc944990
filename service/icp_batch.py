"""``refine="icp-plane"``'s two stages for many start poses of one source at once (the candidates' short refinements).

:func:`refine_plane_many` gives each start the updates :func:`service.icp.refine_plane` would give it (equal to
rounding: the sums run over every source point with the unpaired ones weighted 0): per iteration one KD-tree query
for the moved source of every start still running, and one batched 6x6 solve. A start stops on its own where the
single-start stages would: converged, too few pairs, a degenerate system, or (the precise stage) a limit cycle; a
degenerate precise stage continues with point-to-point :func:`service.icp.icp` for that start, as there. Ranking
the rotation search's candidates took ~30 short refinements per searched registration, one start at a time.
"""

from __future__ import annotations

import numpy as np

from service.icp import (
    PLANE_MIN_EIGEN_RATIO,
    PLANE_MIN_INLIERS,
    WIDE_DISTANCE_FACTOR,
    WIDE_TOLERANCE,
    PairingHistory,
    Surface,
    icp,
    plane_jacobian,
    rms_radius,
)
from service.procrustes import compose


def refine_plane_many(src: np.ndarray, tgt: np.ndarray, R0: np.ndarray, t0: np.ndarray, *, max_distance: float,
                      max_iterations: int, target: Surface, source: Surface,
                      tolerance: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """:func:`service.icp.refine_plane` of ``src [N, 3]`` onto ``tgt [M, 3]`` from each start ``R0 [C, 3, 3]``,
    ``t0 [C, 3]``: the wide symmetric stage at ``WIDE_DISTANCE_FACTOR * max_distance``, then the reciprocal
    point-to-plane stage at ``max_distance``, each at most ``max_iterations`` updates. ``target`` / ``source``:
    ``Surface.of(tgt)`` / ``Surface.of(src)``. Returns the refined ``R [C, 3, 3]``, ``t [C, 3]``."""
    src, tgt = np.asarray(src, dtype=np.float64), np.asarray(tgt, dtype=np.float64)
    R, t = np.array(R0, dtype=np.float64), np.array(t0, dtype=np.float64)  # copies: updated in place
    if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (len(R), 3):
        raise ValueError(f"R0 must be (C, 3, 3) and t0 (C, 3), got {R.shape} and {t.shape}")
    scale = rms_radius(tgt)
    _symmetric_stage(src, tgt, R, t, WIDE_DISTANCE_FACTOR * max_distance, max_iterations, target, source, scale)
    _plane_stage(src, tgt, R, t, max_distance, max_iterations, tolerance, target, source, scale)
    return R, t


def _symmetric_stage(src: np.ndarray, tgt: np.ndarray, R: np.ndarray, t: np.ndarray, max_distance: float,
                     max_iterations: int, target: Surface, source: Surface, scale: float) -> None:
    """:func:`service.icp.icp_symmetric`'s updates of every start, applied to ``R [C, 3, 3]``, ``t [C, 3]``."""
    sigma2 = (max_distance / 3.0) ** 2
    running = np.arange(len(R))
    for _ in range(max_iterations):
        if running.size == 0:
            return
        moved, nearest, pair = _nearest(target, tgt, src, R[running], t[running], max_distance)  # [A, N, 3], [A, N]
        pair &= target.defined[nearest]
        n_t = target.normals[nearest]  # [A, N, 3]
        n_s = source.normals @ R[running].transpose(0, 2, 1)  # [A, N, 3] source normals in the target frame
        n_s *= np.where(np.einsum("anc,anc->an", n_s, n_t) < 0, -1.0, 1.0)[..., None]
        n = np.where(source.defined[None, :, None], n_s + n_t, n_t)  # [A, N, 3]
        with np.errstate(invalid="ignore", divide="ignore"):  # unpaired rows may have no normal: zeroed below
            n = np.where(pair[..., None], n / np.linalg.norm(n, axis=2, keepdims=True), 0.0)
        r = np.einsum("anc,anc->an", n, moved - tgt[nearest])  # [A, N] signed residuals (0 unpaired)
        w = (sigma2 / (sigma2 + r * r)) ** 2 * pair  # [A, N] Geman-McClure weights, 0 unpaired
        ok = np.count_nonzero(pair, axis=1) >= PLANE_MIN_INLIERS  # [A]
        R_step, t_step, rotated, shifted, solved = _plane_steps(moved[ok], n[ok], r[ok], w[ok], scale)
        updated = running[ok][solved]
        R[updated], t[updated] = compose(R_step[solved], t_step[solved], R[updated], t[updated])
        still = (rotated[solved] >= WIDE_TOLERANCE) | (shifted[solved] >= WIDE_TOLERANCE * scale)
        running = updated[still]


def _plane_stage(src: np.ndarray, tgt: np.ndarray, R: np.ndarray, t: np.ndarray, max_distance: float,
                 max_iterations: int, tolerance: float, target: Surface, source: Surface, scale: float) -> None:
    """:func:`service.icp.icp_plane`'s (reciprocal) updates of every start, applied to ``R``, ``t`` in place."""
    running = np.arange(len(R))
    histories = [PairingHistory() for _ in range(len(R))]
    for done in range(max_iterations):
        if running.size == 0:
            return
        moved, nearest, pair = _nearest(target, tgt, src, R[running], t[running], max_distance)  # [A, N, 3], [A, N]
        rows, cols = np.nonzero(pair)  # mutual check: is the source point its partner's nearest source point?
        back = np.einsum("kc,kcd->kd", tgt[nearest[rows, cols]] - t[running[rows]], R[running[rows]])  # R^T (q - t)
        pair[rows, cols] = source.tree.query(back, k=1)[1] == cols
        pair &= target.defined[nearest]
        cycled = np.array([histories[c].recurred(pair[a], nearest[a]) for a, c in enumerate(running)], dtype=bool)
        ok = ~cycled & (np.count_nonzero(pair, axis=1) >= PLANE_MIN_INLIERS)  # [A]
        n = target.normals[nearest] * pair[..., None]  # [A, N, 3], 0 unpaired
        r = np.einsum("anc,anc->an", n, moved - tgt[nearest])  # [A, N]
        R_step, t_step, rotated, shifted, solved = _plane_steps(moved[ok], n[ok], r[ok], pair[ok].astype(float),
                                                                scale)
        for c in running[ok][~solved]:  # degenerate: point-to-point ICP from here, as icp_plane does
            rest = icp(src, tgt, R[c], t[c], max_distance=max_distance, max_iterations=max_iterations - done,
                       tolerance=tolerance)
            R[c], t[c] = rest.rotation, rest.translation
        updated = running[ok][solved]
        R[updated], t[updated] = compose(R_step[solved], t_step[solved], R[updated], t[updated])
        still = (rotated[solved] >= tolerance) | (shifted[solved] >= tolerance * scale)
        running = updated[still]


def _nearest(surface: Surface, tgt: np.ndarray, src: np.ndarray, R: np.ndarray, t: np.ndarray, max_distance: float):
    """The source moved by each pose ``R [A, 3, 3]``, ``t [A, 3]`` (``[A, N, 3]``), each moved point's nearest target
    row (``[A, N]``, clipped into the target) and whether it lies closer than ``max_distance`` (``[A, N]``)."""
    moved = src @ R.transpose(0, 2, 1) + t[:, None]  # [A, N, 3]
    dist, nearest = surface.tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=max_distance)
    nearest = np.minimum(nearest, len(tgt) - 1).reshape(moved.shape[:2])  # misses are not paired
    return moved, nearest, (dist < max_distance).reshape(moved.shape[:2])


def _plane_steps(p: np.ndarray, n: np.ndarray, r: np.ndarray, w: np.ndarray, scale: float):
    """:func:`service.icp._plane_step` of ``B`` starts at once: points ``p [B, N, 3]``, normals ``n``, residuals
    ``r [B, N]`` and weights ``w [B, N]`` (0: not a pair). Returns ``R_step [B, 3, 3]``, ``t_step [B, 3]``, the
    rotation angles and translation lengths ``[B]``, and which systems were solved ``[B]`` (the rest are
    degenerate: smallest eigenvalue below ``PLANE_MIN_EIGEN_RATIO`` of the largest)."""
    centre = np.einsum("bn,bnc->bc", w, p) / w.sum(axis=1)[:, None]  # [B, 3]
    J = plane_jacobian(p, n, centre, scale)  # [B, N, 6]
    Jw = J * w[..., None]
    H = Jw.transpose(0, 2, 1) @ J  # [B, 6, 6]
    g = -np.einsum("bnk,bn->bk", Jw, r) / scale  # [B, 6]
    values, vectors = np.linalg.eigh(H)  # ascending
    solved = values[:, 0] > PLANE_MIN_EIGEN_RATIO * values[:, -1]  # [B]
    safe = np.where(solved[:, None], values, 1.0)
    x = np.einsum("bij,bj->bi", vectors, np.einsum("bji,bj->bi", vectors, g) / safe)  # [B, 6] = H^-1 g
    rotvec, tau = x[:, :3], x[:, 3:] * scale
    angle = np.linalg.norm(rotvec, axis=1)  # [B]
    R_step = rotations_of(rotvec, angle)
    t_step = centre + tau - np.einsum("bij,bj->bi", R_step, centre)
    return R_step, t_step, angle, np.linalg.norm(tau, axis=1), solved


def rotations_of(rotvec: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """:func:`service.icp.rotation_of` of each axis-angle vector ``rotvec [B, 3]`` of norm ``angle [B]``:
    ``[B, 3, 3]``."""
    x, y, z = rotvec[:, 0], rotvec[:, 1], rotvec[:, 2]
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=1).reshape(-1, 3, 3)  # [B, 3, 3]
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)
