"""The fused training matcher layers (model.pair_fused) and a whole fused training step against eager."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from shapes import sphere_shapes

from model.config import MFGNetConfig
from model.data import PairProtocol, make_pairs
from model.losses import registration_losses, sample_training_keypoints
from model.network import MFGNet
from model.pair_fused import first_layer_statistics


def relative_error(got: torch.Tensor, want: torch.Tensor) -> float:
    """Largest error relative to the largest entry (at least 1e-3: gradients that cancel to ~0)."""
    return float((got - want).abs().max().detach() / want.abs().max().clamp_min(1e-3).detach())


def run(module, inputs: list[torch.Tensor]):
    """Forward + backward of a fixed weighted sum -> output, input gradients, parameter gradients."""
    inputs = [x.clone().requires_grad_() for x in inputs]
    for p in module.parameters():
        p.grad = None
    out = module(*inputs)
    weights = torch.linspace(-1.0, 1.0, out.shape[-1], dtype=out.dtype)
    (out * weights).sum().backward()
    return out.detach(), [x.grad for x in inputs], {n: p.grad.clone() for n, p in module.named_parameters()}


def assert_same(fused, eager, inputs, gradient_tolerance: float = 1e-10) -> None:
    out_f, in_f, par_f = run(fused, inputs)
    out_e, in_e, par_e = run(eager, inputs)
    assert relative_error(out_f, out_e) < 1e-10
    for got, want in zip(in_f, in_e, strict=True):
        assert relative_error(got, want) < gradient_tolerance
    for name, want in par_e.items():
        assert relative_error(par_f[name], want) < gradient_tolerance, name
    for (name, got), (_, want) in zip(fused.named_buffers(), eager.named_buffers(), strict=True):
        assert torch.allclose(got.double(), want.double(), rtol=0, atol=1e-12), name


def fused_and_eager(module):
    eager = copy.deepcopy(module)
    for m in eager.modules():
        if hasattr(m, "fused"):
            m.fused = False
    return module, eager


@pytest.mark.parametrize("which", ["feature", "coord"])
def test_fused_pair_mlp_equals_the_eager_one_in_float64(which):
    torch.manual_seed(1)
    mlp = getattr(MFGNet(MFGNetConfig()).double().train().matchers[0], which)
    dims = 64 if which == "feature" else 3
    a, b = torch.randn(3, 40, dims, dtype=torch.float64), torch.randn(3, 50, dims, dtype=torch.float64)
    b[:, 0] = a[:, 0]  # coincident: ||d|| = 0, inv = 1 / eps
    b[:, 1] = a[:, 1] + 1e-5  # nearly: enters the statistics explicitly (CLOSE_PAIR)
    inputs = [a, b, a.clone()] if which == "coord" else [a, b]  # the coordinate matcher's extra term: xyz
    # gradients grow as 1 / ||d|| at the near-coincident pair: ill-conditioned, hence 1e-7
    assert_same(*fused_and_eager(mlp), inputs, gradient_tolerance=1e-7)


def test_fused_credibility_head_equals_the_eager_one_in_float64():
    torch.manual_seed(2)
    head = MFGNet(MFGNetConfig()).double().train().matchers[0].credibility
    F_mat, S_mat = torch.randn(3, 40, 50, dtype=torch.float64), torch.randn(3, 40, 50, dtype=torch.float64)
    assert_same(*fused_and_eager(head), [F_mat, S_mat])


def test_first_layer_statistics_equal_those_of_the_explicit_pairs():
    torch.manual_seed(3)
    B, K, L, C = 2, 30, 20, 8
    pa, pe = torch.randn(B, K, C, dtype=torch.float64), torch.randn(B, K, C, dtype=torch.float64)
    pb, w = torch.randn(B, L, C, dtype=torch.float64), torch.randn(C, dtype=torch.float64)
    dist = torch.rand(B, K, L, dtype=torch.float64) + 0.1
    inv = 1.0 / dist
    z = inv[..., None] * (pa[:, :, None] - pb[:, None]) + dist[..., None] * w + pe[:, :, None]  # [B, K, L, C]
    mean, var = first_layer_statistics(pa, pb, pe, w, inv, dist)
    var_ref, mean_ref = torch.var_mean(z.reshape(-1, C), dim=0, unbiased=False)
    assert torch.allclose(mean, mean_ref, atol=1e-12) and torch.allclose(var, var_ref, atol=1e-12)


def test_a_fused_training_step_equals_the_eager_one_in_float64():
    """Network, keypoint sampling, the three losses and every parameter's gradient, fused vs eager."""
    torch.manual_seed(4)
    cfg = MFGNetConfig(train_positives=24, train_negatives=24)
    fused = MFGNet(cfg).double().train()
    eager = copy.deepcopy(fused)
    eager.set_fused_training(False)
    pairs = make_pairs(sphere_shapes(2, seed=4), PairProtocol(points=300, keep=240), np.random.default_rng(4))
    src, tgt, R, t = (torch.from_numpy(pairs[k]).double() for k in ("source", "target", "rotation", "translation"))
    generator = torch.Generator().manual_seed(0)
    src_idx, tgt_idx = sample_training_keypoints(src, tgt, R, t, 24, 24, cfg.match_threshold, generator)
    losses = {}
    for name, model in (("fused", fused), ("eager", eager)):
        out = model(src, tgt, src_idx=src_idx, tgt_idx=tgt_idx)
        terms = registration_losses(out, src, tgt, R, t, cfg.match_threshold)
        terms.total.backward()
        losses[name] = (terms.total.detach(), out.rotation.detach())
    assert abs(float(losses["fused"][0] - losses["eager"][0])) < 1e-10
    assert torch.allclose(losses["fused"][1], losses["eager"][1], atol=1e-10)
    for (name, p_f), (_, p_e) in zip(fused.named_parameters(), eager.named_parameters(), strict=True):
        assert relative_error(p_f.grad, p_e.grad) < 1e-9, name
    for (name, b_f), (_, b_e) in zip(fused.named_buffers(), eager.named_buffers(), strict=True):
        assert torch.allclose(b_f.double(), b_e.double(), rtol=0, atol=1e-12), name
