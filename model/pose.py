"""Weighted Procrustes (Kabsch) with a reflection guard — the torch twin of ``service.procrustes``."""

from __future__ import annotations

import torch

ZERO_WEIGHT_TOL = 1e-12  # as service.procrustes: uniform weights below it, the exact sum's normalisation above


def weighted_procrustes(
    src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None = None, centroid: str = "weighted"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid ``src_to_tgt`` pose minimising ``sum_i w_i ||R src_i + t - tgt_i||^2``.

    Args:
        src, tgt: ``(B, K, 3)`` corresponding points.
        weights: ``(B, K)`` non-negative weights, normalised here; all-zero rows become uniform.
        centroid: ``"weighted"`` (exact weighted least squares) or ``"unweighted"`` (the authors'
            released variant: plain means in the cross-covariance, weighted sums for ``t``).

    Returns:
        ``R (B, 3, 3)`` with ``det R = +1`` and ``t (B, 3)``.
    """
    if src.shape != tgt.shape or src.shape[-1] != 3 or src.dim() != 3:
        raise ValueError(f"src and tgt must both be (B, K, 3); got {tuple(src.shape)} and {tuple(tgt.shape)}")
    if centroid not in ("weighted", "unweighted"):
        raise ValueError(f"centroid must be 'weighted' or 'unweighted', got {centroid!r}")
    if weights is None:
        weights = torch.ones(src.shape[:-1], dtype=src.dtype, device=src.device)
    w = weights.clamp_min(0)  # [B, K]
    total = w.sum(dim=-1, keepdim=True)  # [B, 1]
    w = torch.where(total > ZERO_WEIGHT_TOL, w, torch.ones_like(w))
    w = w / w.sum(dim=-1, keepdim=True)  # [B, K] summing to 1

    src_sum = torch.einsum("bk,bkc->bc", w, src)  # [B, 3]
    tgt_sum = torch.einsum("bk,bkc->bc", w, tgt)
    if centroid == "weighted":
        src_c, tgt_c = src - src_sum[:, None], tgt - tgt_sum[:, None]
    else:
        src_c, tgt_c = src - src.mean(dim=1, keepdim=True), tgt - tgt.mean(dim=1, keepdim=True)
    H = torch.einsum("bk,bki,bkj->bij", w, src_c, tgt_c)  # [B, 3, 3]
    U, _, Vh = torch.linalg.svd(H.double())
    V, Ut = Vh.transpose(1, 2), U.transpose(1, 2)
    d = torch.sign(torch.linalg.det(V @ Ut))  # [B]
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))  # [B, 3, 3]
    R = (V @ D @ Ut).to(src.dtype)  # [B, 3, 3]
    t = tgt_sum - torch.einsum("bij,bj->bi", R, src_sum)  # [B, 3]
    return R, t


def compose(R_next: torch.Tensor, t_next: torch.Tensor, R: torch.Tensor,
            t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose of applying ``(R, t)`` then ``(R_next, t_next)``."""
    return R_next @ R, torch.einsum("bij,bj->bi", R_next, t) + t_next


def transform_points(points: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``R p + t`` for ``points (B, N, 3)``, ``R (B, 3, 3)``, ``t (B, 3)``."""
    return points @ R.transpose(1, 2) + t[:, None]
