"""Weighted Procrustes (Kabsch) with a reflection guard — the numpy twin of ``model.pose``.

One definition of the pose step is used everywhere: training (torch twin), export parity and
the runtime. Both twins follow exactly the same rules, tested against each other.
"""

from __future__ import annotations

import numpy as np

# Below this total weight the weights are replaced by uniform ones; above it they are divided by their exact sum (the
# paper's credibility normalisation adds 1e-8 to the sum instead, which leaves tiny weights summing to less than 1 and
# pulls both centroids towards the origin).
ZERO_WEIGHT_TOL = 1e-12


def weighted_procrustes(
    src: np.ndarray, tgt: np.ndarray, weights: np.ndarray | None = None, centroid: str = "weighted"
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid ``src_to_tgt`` pose minimising ``sum_i w_i ||R src_i + t - tgt_i||^2``.

    Args:
        src: ``(..., K, 3)`` points in the source frame.
        tgt: ``(..., K, 3)`` corresponding points in the target frame.
        weights: ``(..., K)`` non-negative weights (normalised here); ``None`` means uniform.
            All-zero weights fall back to uniform weights.
        centroid: ``"weighted"`` (exact weighted least squares, the project's choice) or
            ``"unweighted"`` (the authors' released code: plain means in the cross-covariance,
            weighted sums for the translation).

    Returns:
        ``R`` ``(..., 3, 3)`` with ``det R = +1`` and ``t`` ``(..., 3)``, in ``src``'s dtype.
    """
    if src.shape != tgt.shape or src.shape[-1] != 3 or src.ndim < 2:
        raise ValueError(f"src and tgt must both be (..., K, 3); got {src.shape} and {tgt.shape}")
    if centroid not in ("weighted", "unweighted"):
        raise ValueError(f"centroid must be 'weighted' or 'unweighted', got {centroid!r}")
    dtype = np.result_type(src.dtype, np.float32)
    src = src.astype(np.float64, copy=False)
    tgt = tgt.astype(np.float64, copy=False)
    if weights is None:
        weights = np.ones(src.shape[:-1])
    if weights.shape != src.shape[:-1]:
        raise ValueError(f"weights must be {src.shape[:-1]}, got {weights.shape}")
    w = np.clip(weights.astype(np.float64), 0.0, None)  # [..., K]
    total = w.sum(axis=-1, keepdims=True)  # [..., 1]
    w = np.where(total > ZERO_WEIGHT_TOL, w, 1.0)
    w = w / w.sum(axis=-1, keepdims=True)  # [..., K] summing to 1

    # matrix products rather than einsum: 2x faster on batches ([13, 384]: 1.0 -> 0.48 ms), equal to ~1e-15
    src_sum = (w[..., None, :] @ src)[..., 0, :]  # [..., 3] weighted sums
    tgt_sum = (w[..., None, :] @ tgt)[..., 0, :]
    if centroid == "weighted":
        src_c = src - src_sum[..., None, :]
        tgt_c = tgt - tgt_sum[..., None, :]
    else:
        src_c = src - src.mean(axis=-2, keepdims=True)
        tgt_c = tgt - tgt.mean(axis=-2, keepdims=True)
    H = np.swapaxes(src_c * w[..., None], -1, -2) @ tgt_c  # [..., 3, 3] = sum_k w_k src_c_k tgt_c_k^T
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(U @ Vt))  # [...] = det(V U^T)
    V[..., :, 2] *= np.where(d == 0, 1.0, d)[..., None]  # V diag(1, 1, d): the reflection guard
    R = V @ np.swapaxes(U, -1, -2)  # [..., 3, 3]
    t = tgt_sum - (R @ src_sum[..., None])[..., 0]  # [..., 3]
    return R.astype(dtype), t.astype(dtype)


def compose(R_next: np.ndarray, t_next: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose of applying ``(R, t)`` then ``(R_next, t_next)``: ``R_next R``, ``R_next t + t_next``."""
    return R_next @ R, np.einsum("...ij,...j->...i", R_next, t) + t_next


def to_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` homogeneous transform from ``R (..., 3, 3)`` and ``t (..., 3)``."""
    T = np.zeros((*R.shape[:-2], 4, 4), dtype=R.dtype)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T
