"""The fused training edge convolution (model.edge_fused) against the eager block it replaces."""

from __future__ import annotations

import copy

import pytest
import torch

import model.edge_fused as edge_fused
from model.config import MFGNetConfig
from model.network import MFGNet, knn_indices


def encoder_run(encoder, points: torch.Tensor, neighbours: torch.Tensor):
    """Forward + backward of a fixed weighted sum; returns the output and every parameter's gradient."""
    for p in encoder.parameters():
        p.grad = None
    out = encoder(points, neighbours)  # [B, N, D]
    weights = torch.linspace(-1.0, 1.0, out.shape[-1], dtype=out.dtype)
    (out * weights).sum().backward()
    return out.detach(), {n: p.grad.clone() for n, p in encoder.named_parameters()}


def fused_and_eager(dtype=torch.float64):
    torch.manual_seed(3)
    fused = MFGNet(MFGNetConfig()).encoder.to(dtype).train()
    eager = copy.deepcopy(fused)
    eager.fused = False
    return fused, eager


@pytest.mark.parametrize("chunk", [64, 1024])
def test_fused_encoder_equals_the_eager_one_in_float64(monkeypatch, chunk):
    monkeypatch.setattr(edge_fused, "CHUNK_POINTS", chunk)  # 64: many chunks, the last one partial
    fused, eager = fused_and_eager()
    points = torch.rand(2, 150, 3, dtype=torch.float64)
    neighbours = knn_indices(points, 12)
    out_f, grads_f = encoder_run(fused, points, neighbours)
    out_e, grads_e = encoder_run(eager, points, neighbours)
    assert torch.allclose(out_f, out_e, rtol=0, atol=1e-10)
    for name, grad in grads_e.items():
        scale = grad.abs().max().clamp_min(1e-3)  # biases cancelled by the next block have ~0 gradient
        assert (grads_f[name] - grad).abs().max() / scale < 1e-8, name
    for (name, buf_f), (_, buf_e) in zip(fused.named_buffers(), eager.named_buffers(), strict=True):
        assert torch.allclose(buf_f.double(), buf_e.double(), rtol=0, atol=1e-12), name


def test_fused_path_is_training_only():
    fused, eager = fused_and_eager(torch.float32)
    points = torch.rand(2, 100, 3)
    fused.eval()
    eager.eval()
    assert torch.equal(fused(points), eager(points))  # eval: the eager block, bit for bit
    fused.train()
    with torch.no_grad():
        running = fused.blocks[0].edge.bn.running_mean.clone()
        fused(points)
    assert not torch.equal(running, fused.blocks[0].edge.bn.running_mean)  # no_grad training still updates BN


def test_edge_statistics_equal_those_of_the_explicit_edges():
    torch.manual_seed(0)
    y = torch.randn(300, 16, dtype=torch.float64)
    nbr = torch.randint(0, 300, (300, 12))
    edges = y[nbr] - y[:, None]  # [P, k, C]
    mean, var = edge_fused.edge_statistics(y, edge_fused.edge_graph(nbr, y.dtype))
    var_ref, mean_ref = torch.var_mean(edges.reshape(-1, 16), dim=0, unbiased=False)
    assert torch.allclose(mean, mean_ref, atol=1e-12)
    assert torch.allclose(var, var_ref, atol=1e-12)


def test_duplicate_points_give_the_eager_parameter_gradients():
    """Duplicated points tie for the maximum: the fused block shares the gradient between them
    (the eager block gives it to one), which leaves every parameter's gradient unchanged."""
    fused, eager = fused_and_eager()
    base = torch.rand(1, 80, 3, dtype=torch.float64)
    points = torch.cat([base, base[:, :40]], dim=1)  # 40 points twice
    neighbours = knn_indices(points, 12)
    _, grads_f = encoder_run(fused, points, neighbours)
    _, grads_e = encoder_run(eager, points, neighbours)
    for name, grad in grads_e.items():
        assert torch.isfinite(grads_f[name]).all(), name
        scale = grad.abs().max().clamp_min(1e-3)  # biases cancelled by the next block have ~0 gradient
        assert (grads_f[name] - grad).abs().max() / scale < 1e-8, name
