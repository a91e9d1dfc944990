"""Training-time edge convolution with far fewer passes over the ``[B, k, N, C]`` edge tensors.

The edge block computes ``max_k relu(BN(W x_j - W x_i)) W2^T``. Eager PyTorch runs every step of it
as a separate pass over all ``B x k x N`` edges (gather, subtract, BatchNorm statistics and
normalisation, ReLU, linear, max, and as many backward passes: ~40 MB each at batch 8), and on a
2-core machine with a 32 MB L3 cache those passes are bound by memory bandwidth. Here:

* the BatchNorm statistics of the edge features are computed exactly from per-point sums (the
  neighbour in-degree and the neighbour sum ``S_i = sum_j y_j``, a sparse product), so BN becomes a
  per-point affine map folded into the two per-point terms ``u_j - v_i``;
* gather, subtract, ReLU, linear and max run chunk by chunk (a chunk's intermediates stay in cache),
  and so does the backward pass; only the ReLU output and the linear output are kept for it.

Outputs, gradients and running statistics equal the eager block's up to float rounding (in float64
to ~1e-13; in float32 closer to a float64 reference than the eager block is), except that edges tied
for a maximum share its gradient, as ``torch.amax`` does, where ``max`` gives it to one of them.
``model.network.Encoder`` uses it for CPU training; evaluation and ONNX export run the eager block.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import nn
from torch.autograd.function import FunctionCtx

from model.fused_common import chunks, fold_batch_statistics, max_gradient

CHUNK_POINTS = 1024  # points per chunk: 1024 x 12 x 64 floats = 3 MB per intermediate (512-4096 measured)


class NeighbourSum(torch.autograd.Function):
    """``S = A y`` with the adjacency ``A [P, P]`` (``A[i, j]`` = times ``j`` is a neighbour of ``i``) and
    its transpose given as CSR matrices (one sparse product each way, ~1.6x faster than 12 gathers)."""

    @staticmethod
    def forward(ctx: FunctionCtx, y: torch.Tensor, adjacency: torch.Tensor, adjacency_t: torch.Tensor) -> torch.Tensor:
        ctx.adjacency_t = adjacency_t
        return adjacency @ y

    @staticmethod
    def backward(ctx: FunctionCtx, grad_s: torch.Tensor):
        return ctx.adjacency_t @ grad_s, None, None


@dataclass(frozen=True)
class EdgeGraph:
    """A batch's k-NN graph in the forms the fused block uses, built once per encoder pass."""

    nbr: torch.Tensor  # [P, k] flat row indices of each point's neighbours (itself included)
    adjacency: torch.Tensor  # [P, P] CSR, A[i, j] = times j is a neighbour of i
    adjacency_t: torch.Tensor  # [P, P] CSR, A^T
    degree: torch.Tensor  # [P] float64: times each point is a neighbour (A^T 1)


def edge_graph(nbr: torch.Tensor, dtype: torch.dtype) -> EdgeGraph:
    """``nbr [P, k]`` -> :class:`EdgeGraph` with ``dtype`` matrices."""
    P, k = nbr.shape
    device = nbr.device
    ones = torch.ones(P * k, dtype=dtype, device=device)
    cols = nbr.reshape(-1)
    degree = torch.bincount(cols, minlength=P)  # [P]
    crow = torch.zeros(P + 1, dtype=torch.long, device=device)
    crow[1:] = degree.cumsum(0)
    rows = torch.arange(P, device=device).repeat_interleave(k)[torch.argsort(cols, stable=True)]
    with warnings.catch_warnings():  # "sparse CSR support is in beta": used for two products only, tested
        warnings.simplefilter("ignore", UserWarning)
        adjacency = torch.sparse_csr_tensor(
            torch.arange(0, P * k + 1, k, device=device), cols, ones, (P, P), check_invariants=False
        )
        adjacency_t = torch.sparse_csr_tensor(crow, rows, ones, (P, P), check_invariants=False)
    return EdgeGraph(nbr, adjacency, adjacency_t, degree.double())


class EdgeReluLinearMax(torch.autograd.Function):
    """``m_i = max_k relu(u[nbr[i, k]] - v_i) W^T``: ``u, v [P, C]``, ``nbr [P, k]``, ``W [D, C]``
    -> ``[P, D]``. Edges tied for a maximum share its gradient equally (as ``torch.amax``)."""

    @staticmethod
    def forward(ctx: FunctionCtx, u: torch.Tensor, v: torch.Tensor, nbr: torch.Tensor,
                weight: torch.Tensor) -> torch.Tensor:
        P, k = nbr.shape
        out = u.new_empty(P, weight.shape[0])
        hidden = u.new_empty(P, k, u.shape[1])  # [P, k, C] relu(u_j - v_i), kept for the backward
        edges_out = u.new_empty(P, k, weight.shape[0])  # [P, k, D] kept: the backward needs where the max was
        for s in chunks(P, CHUNK_POINTS):
            h = _edge_hidden(u, v, nbr, s, out=hidden[s])
            o = torch.matmul(h, weight.t(), out=edges_out[s])  # [p, k, D]
            torch.amax(o, dim=1, out=out[s])
        ctx.save_for_backward(nbr, weight, out, edges_out, hidden)
        return out

    @staticmethod
    def backward(ctx: FunctionCtx, grad_m: torch.Tensor):
        nbr, weight, out, edges_out, hidden = ctx.saved_tensors
        C, D = hidden.shape[2], weight.shape[0]
        grad_u = hidden.new_zeros(nbr.shape[0], C)  # u has a row per point, as nbr
        grad_v = hidden.new_empty(nbr.shape[0], C)
        grad_w = torch.zeros_like(weight)
        for s in chunks(nbr.shape[0], CHUNK_POINTS):
            h = hidden[s]  # [p, k, C]
            grad_o = max_gradient(edges_out[s], out[s], grad_m[s], out=torch.empty_like(edges_out[s]))  # [p, k, D]
            grad_w.addmm_(grad_o.view(-1, D).t(), h.view(-1, C))
            grad_h = torch.ops.aten.threshold_backward(torch.matmul(grad_o, weight), h, 0.0)  # ReLU
            grad_u.index_add_(0, nbr[s].reshape(-1), grad_h.view(-1, C))
            torch.sum(grad_h, dim=1, out=grad_v[s])
        grad_v.neg_()
        return grad_u, grad_v, None, grad_w


def _edge_hidden(u: torch.Tensor, v: torch.Tensor, nbr: torch.Tensor, rows: slice, out: torch.Tensor) -> torch.Tensor:
    """``relu(u[nbr[i, k]] - v_i)`` for the points ``rows``, written to ``out [p, k, C]``."""
    torch.index_select(u, 0, nbr[rows].reshape(-1), out=out.view(-1, u.shape[1]))
    return out.sub_(v[rows, None]).relu_()


def edge_statistics(y: torch.Tensor, graph: EdgeGraph) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and biased variance per channel of the edge features ``y[nbr[i, k]] - y_i`` over all
    ``P x k`` edges, from per-point sums (differentiable): ``y [P, C]`` -> ``[C], [C]``."""
    P, k = graph.nbr.shape
    count = P * k
    cross = y * NeighbourSum.apply(y, graph.adjacency, graph.adjacency_t)  # [P, C] y_i * sum_j y_j
    y = y.double()  # the variance is a difference of sums: accumulate in float64 (cheap at [P, C])
    y2 = y * y
    sum_e = graph.degree @ y - k * y.sum(0)  # [C]
    sum_e2 = graph.degree @ y2 - 2.0 * cross.double().sum(0) + k * y2.sum(0)
    mean = sum_e / count
    dtype = cross.dtype
    return mean.to(dtype), (sum_e2 / count - mean * mean).to(dtype)


def fused_edge_max(y: torch.Tensor, graph: EdgeGraph, bn: nn.BatchNorm1d, weight: torch.Tensor) -> torch.Tensor:
    """Training-mode ``max_k relu(BN(y_j - y_i)) W^T`` (no bias) with batch statistics; updates ``bn``'s
    running statistics as ``nn.BatchNorm1d`` does. ``y [P, C]`` -> ``[P, D]``."""
    mean, var = edge_statistics(y, graph)
    scale, shift = fold_batch_statistics(bn, mean, var, graph.nbr.numel())
    u = y * scale  # BN(y_j - y_i) = u_j - v_i
    return EdgeReluLinearMax.apply(u, u - shift, graph.nbr, weight)
