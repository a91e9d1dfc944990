"""Training-time matcher layers: the pair MLPs and the credibility max without eager's extra passes.

Each ``PairMLP`` runs over every (source i, target j) keypoint pair: ``[B, K, L, C]`` tensors of 16 MB
at batch 8 (K = L = 128, C = 32), where eager PyTorch spends most of its time in memory-bound passes
(broadcasts, BatchNorm statistics and normalisation, ReLU, and their backward passes). Here:

* the first layer ``z_ij = inv_ij (pa_i - pb_j) + dist_ij w + pe_i`` (``inv = 1 / (dist + eps)``,
  after the per-point rewrite) gets its BatchNorm statistics in closed form from sums over the small
  ``[B, K, L]`` and ``[B, K, C]`` tensors, so BN folds into ``pa, pb, w, pe``;
* every later BatchNorm gets its statistics from the previous layer's output moments ``sum a^T a`` and
  ``sum a``, taken while each chunk is in cache (``mean = W m / n``, ``E[z^2] = diag(W G W^T) / n``), so
  BN folds into the layer's weight and a shift;
* each layer, the score head and the credibility head's ``max_j (F_ij w0 + S_ij w1)`` run one batch
  element at a time (2 MB), forward and backward.

Outputs, gradients and running statistics equal the eager layers' up to float rounding (float64:
~1e-13, ``tests/model/test_pair_fused.py``, including a whole training step). Evaluation and ONNX
export run the eager layers.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.autograd.function import FunctionCtx

from model.fused_common import chunks, fold_batch_statistics, max_gradient


class _Moments:
    """Running ``sum a^T a`` ``[C, C]`` and ``sum a`` ``[C]`` (float64) of a layer's output chunks: the
    next BatchNorm's statistics, taken while each chunk is in cache."""

    def __init__(self, channels: int):
        self.gram = torch.zeros(channels, channels, dtype=torch.float64)
        self.total = torch.zeros(channels, dtype=torch.float64)

    def add(self, a: torch.Tensor) -> None:
        self.gram += (a.t() @ a).double()
        self.total += a.sum(0).double()


class _MomentsGrad:
    """The gradient that the moments of an output ``a`` send back to ``a``: ``a (G + G^T) + g_total``."""

    def __init__(self, grad_gram: torch.Tensor, grad_total: torch.Tensor, dtype: torch.dtype):
        self.sym = (grad_gram + grad_gram.t()).to(dtype)  # [C, C]
        self.total = grad_total.to(dtype)  # [C]

    def of(self, grad_a: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """``grad_a [n, C]`` plus the moments' share for the output chunk ``a [n, C]``."""
        return torch.addmm(grad_a, a, self.sym).add_(self.total)


class FirstPairLayer(torch.autograd.Function):
    """``relu(inv_ij (pa_i - pb_j) + dist_ij w + pe_i)``: ``pa, pe [B, K, C]``, ``pb [B, L, C]``,
    ``w [C]``, ``inv, dist [B, K, L]`` -> ``[B, K, L, C]`` and its moments (``_Moments``)."""

    @staticmethod
    def forward(ctx: FunctionCtx, pa: torch.Tensor, pb: torch.Tensor, pe: torch.Tensor, w: torch.Tensor,
                inv: torch.Tensor, dist: torch.Tensor):
        B, K, L = inv.shape
        C = pa.shape[2]
        out = pa.new_empty(B, K, L, C)
        moments = _Moments(C)
        for b in range(B):
            z = torch.sub(pa[b, :, None], pb[b, None], out=out[b])  # [K, L, C]; the difference first, as
            z.mul_(inv[b, :, :, None])  # eager does: inv is up to 1 / eps where pa_i = pb_j
            z.addcmul_(dist[b, :, :, None], w).add_(pe[b, :, None])
            moments.add(z.relu_().view(-1, C))
        ctx.save_for_backward(pa, pb, pe, w, inv, dist, out)
        return out, moments.gram, moments.total

    @staticmethod
    def backward(ctx: FunctionCtx, grad_out: torch.Tensor, grad_gram: torch.Tensor, grad_total: torch.Tensor):
        pa, pb, pe, w, inv, dist, out = ctx.saved_tensors
        B, K, L = inv.shape
        C = pa.shape[2]
        moments_grad = _MomentsGrad(grad_gram, grad_total, pa.dtype)
        grad_pa, grad_pb, grad_pe = torch.empty_like(pa), torch.empty_like(pb), torch.empty_like(pe)
        grad_inv, grad_dist = torch.empty_like(inv), torch.empty_like(dist)
        grad_w = torch.zeros_like(w)
        ones = inv.new_ones(K, 1, L)
        for b in range(B):
            a = out[b].view(-1, C)
            g = torch.ops.aten.threshold_backward(moments_grad.of(grad_out[b].view(-1, C), a), a, 0.0)
            g = g.view(K, L, C)  # through the ReLU
            # sum_j inv_ij g_ijc and sum_j g_ijc: one batched product over i
            row_sums = torch.bmm(torch.cat([inv[b, :, None], ones], dim=1), g)  # [K, 2, C]
            grad_pa[b], grad_pe[b] = row_sums[:, 0], row_sums[:, 1]
            gi = g * inv[b, :, :, None]  # [K, L, C]
            torch.sum(gi, dim=0, out=grad_pb[b]).neg_()
            grad_inv[b] = torch.linalg.vecdot(g, pa[b, :, None] - pb[b, None])  # sum_c g_ijc (pa_ic - pb_jc)
            torch.mv(g.view(-1, C), w, out=grad_dist[b].view(-1))
            grad_w.addmv_(g.view(-1, C).t(), dist[b].reshape(-1))
        return grad_pa, grad_pb, grad_pe, grad_w, grad_inv, grad_dist


class HiddenPairLayer(torch.autograd.Function):
    """``relu(a W^T + shift)`` with BatchNorm folded into ``W [D, C]`` and ``shift [D]``: ``a [n, C]`` ->
    ``[n, D]`` and its moments, one batch element (``rows``) at a time."""

    @staticmethod
    def forward(ctx: FunctionCtx, a: torch.Tensor, weight: torch.Tensor, shift: torch.Tensor, rows: int):
        out = a.new_empty(a.shape[0], weight.shape[0])
        moments = _Moments(weight.shape[0])
        for s in chunks(a.shape[0], rows):
            moments.add(torch.mm(a[s], weight.t(), out=out[s]).add_(shift).relu_())
        ctx.save_for_backward(a, weight, out)
        ctx.rows = rows
        return out, moments.gram, moments.total

    @staticmethod
    def backward(ctx: FunctionCtx, grad_out: torch.Tensor, grad_gram: torch.Tensor, grad_total: torch.Tensor):
        a, weight, out = ctx.saved_tensors
        moments_grad = _MomentsGrad(grad_gram, grad_total, a.dtype)
        grad_a = torch.empty_like(a)
        grad_w, grad_shift = torch.zeros_like(weight), torch.zeros(weight.shape[0], dtype=a.dtype)
        for s in chunks(a.shape[0], ctx.rows):
            g = torch.ops.aten.threshold_backward(moments_grad.of(grad_out[s], out[s]), out[s], 0.0)
            grad_w.addmm_(g.t(), a[s])
            grad_shift += g.sum(0)
            torch.mm(g, weight, out=grad_a[s])
        return grad_a, grad_w, grad_shift, None


class LastPairLayer(torch.autograd.Function):
    """``relu(a W^T + shift) w_head + b_head``: the last hidden layer (BatchNorm folded) and the score
    head, ``a [n, C]`` -> scores ``[n]``, one batch element (``rows``) at a time."""

    @staticmethod
    def forward(ctx: FunctionCtx, a: torch.Tensor, weight: torch.Tensor, shift: torch.Tensor, head_weight: torch.Tensor,
                head_bias: torch.Tensor, rows: int):
        hidden = a.new_empty(a.shape[0], weight.shape[0])  # [n, D] kept for the backward
        scores = a.new_empty(a.shape[0])
        head = head_weight.reshape(-1)  # [D]
        for s in chunks(a.shape[0], rows):
            h = torch.mm(a[s], weight.t(), out=hidden[s]).add_(shift).relu_()  # addmm(out=) was 1.5x slower
            torch.addmv(head_bias, h, head, out=scores[s])
        ctx.save_for_backward(a, weight, hidden, head_weight)
        ctx.rows = rows
        return scores

    @staticmethod
    def backward(ctx: FunctionCtx, grad_scores: torch.Tensor):
        a, weight, hidden, head_weight = ctx.saved_tensors
        head = head_weight.reshape(-1)
        grad_a = torch.empty_like(a)
        grad_w, grad_shift = torch.zeros_like(weight), torch.zeros(weight.shape[0], dtype=a.dtype)
        grad_head = torch.zeros_like(head)
        for s in chunks(a.shape[0], ctx.rows):
            h, gs = hidden[s], grad_scores[s]
            grad_head.addmv_(h.t(), gs)
            g = torch.ops.aten.threshold_backward(torch.outer(gs, head), h, 0.0)  # [rows, D] through the ReLU
            grad_w.addmm_(g.t(), a[s])
            grad_shift += g.sum(0)
            torch.mm(g, weight, out=grad_a[s])
        return grad_a, grad_w, grad_shift, grad_head.view_as(head_weight), grad_scores.sum().view(1), None


class PairMax(torch.autograd.Function):
    """``m_ic = max_j (F_ij w0_c + S_ij w1_c)``: ``F, S [B, K, L]``, ``w0, w1 [C]`` -> ``[B, K, C]`` (the
    credibility head's first layer and max), one batch element at a time; nothing ``[B, K, L, C]`` is
    kept: the backward pass recomputes it. Ties share the gradient (as ``torch.amax``)."""

    @staticmethod
    def forward(ctx: FunctionCtx, F_mat: torch.Tensor, S_mat: torch.Tensor, w0: torch.Tensor, w1: torch.Tensor):
        B, K = F_mat.shape[:2]
        out = F_mat.new_empty(B, K, w0.shape[0])
        for b in range(B):
            torch.amax(_pair_pre(F_mat[b], S_mat[b], w0, w1), dim=1, out=out[b])
        ctx.save_for_backward(F_mat, S_mat, w0, w1, out)
        return out

    @staticmethod
    def backward(ctx: FunctionCtx, grad_out: torch.Tensor):
        F_mat, S_mat, w0, w1, out = ctx.saved_tensors
        C = w0.shape[0]
        grad_F, grad_S = torch.empty_like(F_mat), torch.empty_like(S_mat)
        grad_w0, grad_w1 = torch.zeros_like(w0), torch.zeros_like(w1)
        for b in range(F_mat.shape[0]):
            g = max_gradient(_pair_pre(F_mat[b], S_mat[b], w0, w1), out[b], grad_out[b]).view(-1, C)  # [K * L, C]
            torch.mv(g, w0, out=grad_F[b].view(-1))
            torch.mv(g, w1, out=grad_S[b].view(-1))
            grad_w0.addmv_(g.t(), F_mat[b].reshape(-1))
            grad_w1.addmv_(g.t(), S_mat[b].reshape(-1))
        return grad_F, grad_S, grad_w0, grad_w1


def _pair_pre(F_b: torch.Tensor, S_b: torch.Tensor, w0: torch.Tensor, w1: torch.Tensor) -> torch.Tensor:
    """``F_ij w0_c + S_ij w1_c`` of one batch element: ``[K, L]`` x2 -> ``[K, L, C]``."""
    return torch.mul(F_b[..., None], w0).addcmul_(S_b[..., None], w1)


CLOSE_PAIR = 1e-2  # pairs nearer than this enter the first layer's statistics explicitly (see below)


def first_layer_statistics(pa: torch.Tensor, pb: torch.Tensor, pe: torch.Tensor, w: torch.Tensor, inv: torch.Tensor,
                           dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and biased variance per channel of ``z_ij = inv_ij (pa_i - pb_j) + dist_ij w + pe_i`` over
    all ``B x K x L`` pairs (differentiable; summed in float64): ``[C], [C]``.

    Closed form from sums over ``[B, K, L]`` and ``[B, K, C]`` tensors, except for pairs nearer than
    ``CLOSE_PAIR``: there ``inv`` reaches ``1 / eps`` and the expanded square ``(pa_i - pb_j)^2 inv^2``
    would cancel catastrophically, so their ``z`` is computed explicitly (rarely more than a few
    hundred pairs).
    """
    dtype = pa.dtype
    pa, pb, pe, w, inv, dist = (x.double() for x in (pa, pb, pe, w, inv, dist))
    B, K, L = inv.shape
    n = B * K * L
    far = (dist >= CLOSE_PAIR).to(inv.dtype)  # [B, K, L]
    inv_far, dist_far, count = inv * far, dist * far, far.sum(2)  # close pairs drop out of every sum below
    inv2, inv_dist = inv_far * inv_far, inv_far * dist_far  # [B, K, L]
    row_inv, col_inv = inv_far.sum(2), inv_far.sum(1)  # [B, K], [B, L]

    def rows(x: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:  # sum_b,i x_bic weights_bi -> [C]
        return torch.einsum("bic,bi->c", x, weights)

    sum_z = rows(pa, row_inv) - rows(pb, col_inv) + w * dist_far.sum() + rows(pe, count)
    sum_z2 = (
        rows(pa * pa, inv2.sum(2))
        + rows(pb * pb, inv2.sum(1))
        - 2.0 * (pa * torch.bmm(inv2, pb)).sum((0, 1))  # cross term of (pa_i - pb_j)^2 inv^2
        + w * w * (dist_far * dist_far).sum()
        + rows(pe * pe, count)
        + 2.0 * w * (rows(pa, inv_dist.sum(2)) - rows(pb, inv_dist.sum(1)))
        + 2.0 * (rows(pa * pe, row_inv) - (pe * torch.bmm(inv_far, pb)).sum((0, 1)))
        + 2.0 * w * rows(pe, dist_far.sum(2))
    )
    b, i, j = torch.nonzero(far == 0, as_tuple=True)  # the close pairs
    if b.numel():
        z_close = (pa[b, i] - pb[b, j]) * inv[b, i, j, None] + dist[b, i, j, None] * w + pe[b, i]  # [m, C]
        sum_z = sum_z + z_close.sum(0)  # [C]
        sum_z2 = sum_z2 + (z_close * z_close).sum(0)
    mean = sum_z / n
    return mean.to(dtype), (sum_z2 / n - mean * mean).to(dtype)


def fused_pair_mlp(mlp: nn.Module, pa: torch.Tensor, pb: torch.Tensor, pe: torch.Tensor | None, w: torch.Tensor,
                   inv: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Training-mode scores ``[B, K, L]`` of ``mlp`` (a ``model.network.PairMLP``) with batch statistics;
    running statistics updated as eager BatchNorm does. ``pe`` None: no per-source extra term."""
    B, K, L = inv.shape
    if pe is None:
        pe = pa.new_zeros(pa.shape)
    scale, shift = fold_batch_statistics(mlp.first.bn, *first_layer_statistics(pa, pb, pe, w, inv, dist), inv.numel())
    a, gram, total = FirstPairLayer.apply(pa * scale, pb * scale, pe * scale + shift, w * scale, inv, dist)
    a = a.view(-1, a.shape[-1])  # [n, C]
    n = a.shape[0]
    last = len(mlp.hidden) - 1
    for i, layer in enumerate(mlp.hidden):
        weight = layer.linear.weight  # [D, C]
        w64 = weight.double()
        mean = w64 @ total / n  # [D] mean of a W^T
        var = ((w64 @ gram) * w64).sum(1) / n - mean * mean  # [D] diag(W G W^T) / n - mean^2
        scale, shift = fold_batch_statistics(layer.bn, mean.to(a.dtype), var.to(a.dtype), n)
        if i < last:
            a, gram, total = HiddenPairLayer.apply(a, weight * scale[:, None], shift, K * L)
        else:
            scores = LastPairLayer.apply(a, weight * scale[:, None], shift, mlp.out.weight, mlp.out.bias, K * L)
    return scores.view(B, K, L)
