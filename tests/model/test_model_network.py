"""``model.network``: output shapes, weight sets per iteration, and the exactness of the algebraic rewrites
against naive implementations that build the paper's pair / edge tensors explicitly."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from model.config import MFGNetConfig
from model.network import (
    NORM_EPS,
    BNReLULinear,
    CredibilityHead,
    EdgeConvBlock,
    Encoder,
    MFGNet,
    PairMLP,
    gather_points,
    knn_indices,
    median_threshold_weights,
)
from model.pose import compose

SMALL = MFGNetConfig(keypoints=32)


def randomise_batchnorm(module: nn.Module, seed: int = 0) -> nn.Module:
    """Non-trivial running statistics and affine parameters, so eval-mode BatchNorm is not the identity."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, nn.BatchNorm1d):
                C = m.num_features
                m.running_mean.copy_(0.5 * torch.randn(C, generator=g))
                m.running_var.copy_(0.5 + torch.rand(C, generator=g))
                m.weight.copy_(1.0 + 0.3 * torch.randn(C, generator=g))
                m.bias.copy_(0.3 * torch.randn(C, generator=g))
    return module


def clouds(B: int, N: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    return torch.rand(B, N, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype) * 2 - 1


def bn_relu_linear(layer: BNReLULinear, x: torch.Tensor) -> torch.Tensor:
    """The layer on ``[..., C_in]`` as the paper writes it: FC, then BN over channels, then ReLU."""
    z = layer.linear(x)
    return torch.relu(layer.bn(z.reshape(-1, z.shape[-1])).reshape(z.shape))


# --- shapes and weight sets -----------------------------------------------------------------------


@torch.no_grad()
def test_output_shapes_for_two_pairs_of_256_points_and_32_keypoints() -> None:
    torch.manual_seed(0)
    model = MFGNet(SMALL).eval()
    out = model(clouds(2, 256, 0), clouds(2, 256, 1))
    assert out.rotation.shape == (2, 3, 3)
    assert out.translation.shape == (2, 3)
    assert out.src_idx.shape == out.tgt_idx.shape == (2, 32)
    assert out.src_scores.shape == out.tgt_scores.shape == (2, 256)
    assert len(out.steps) == SMALL.iterations == 4
    for step in out.steps:
        assert step.scores.shape == (2, 32, 32)
        assert step.cred_logit.shape == step.match.shape == step.weights.shape == (2, 32)
        assert step.rotation.shape == (2, 3, 3)
        assert step.translation.shape == (2, 3)
        assert float(step.scores.abs().max()) <= SMALL.clamp
        assert (step.weights > 0).sum(dim=-1).min() >= 16  # the median threshold keeps at least half
    torch.testing.assert_close(torch.linalg.det(out.rotation), torch.ones(2))


@torch.no_grad()
def test_keypoints_are_the_most_significant_points() -> None:
    torch.manual_seed(0)
    model = MFGNet(SMALL).eval()
    out = model(clouds(2, 256, 0), clouds(2, 256, 1))
    for scores, idx in ((out.src_scores, out.src_idx), (out.tgt_scores, out.tgt_idx)):
        kept = scores.gather(1, idx).min(dim=1).values  # [B]
        dropped = scores.scatter(1, idx, float("-inf")).max(dim=1).values
        assert (kept >= dropped).all()


@torch.no_grad()
def test_clouds_of_different_sizes_and_given_keypoints() -> None:
    torch.manual_seed(0)
    model = MFGNet(SMALL).eval()
    src_idx = torch.arange(20).expand(2, 20)
    tgt_idx = torch.arange(30).expand(2, 30)
    out = model(clouds(2, 256, 0), clouds(2, 200, 1), iterations=2, src_idx=src_idx, tgt_idx=tgt_idx)
    assert out.src_scores.shape == (2, 256)
    assert out.tgt_scores.shape == (2, 200)
    assert len(out.steps) == 2
    assert out.steps[0].scores.shape == (2, 20, 30)
    assert torch.equal(out.src_idx, src_idx)


@torch.no_grad()
def test_total_pose_composes_the_iteration_poses() -> None:
    torch.manual_seed(0)
    out = MFGNet(SMALL).eval()(clouds(2, 256, 0), clouds(2, 256, 1))
    R = torch.eye(3).expand(2, 3, 3)
    t = torch.zeros(2, 3)
    for step in out.steps:
        R, t = compose(step.rotation, step.translation, R, t)
    torch.testing.assert_close(out.rotation, R)
    torch.testing.assert_close(out.translation, t)


def test_shared_weights_use_one_matcher_set_for_every_iteration() -> None:
    model = MFGNet(MFGNetConfig(share_weights=True))
    assert len(model.matchers) == 1
    assert all(model.matcher(i) is model.matchers[0] for i in range(6))


def test_each_iteration_has_its_own_matchers_and_later_ones_reuse_the_last() -> None:
    model = MFGNet(MFGNetConfig(iterations=4))
    assert len(model.matchers) == 4
    assert [model.matcher(i) for i in range(4)] == list(model.matchers)
    assert model.matcher(4) is model.matchers[-1]
    assert model.matcher(10) is model.matchers[-1]


@torch.no_grad()
def test_more_iterations_than_trained_weight_sets_runs() -> None:
    torch.manual_seed(0)
    model = MFGNet(MFGNetConfig(iterations=2, keypoints=16, emb_dims=16, encoder_blocks=2)).eval()
    out = model(clouds(1, 64, 0), clouds(1, 64, 1), iterations=5)
    assert len(out.steps) == 5


def test_matcher_layer_widths_follow_the_paper() -> None:
    cfg = MFGNetConfig()
    params = dict(MFGNet(cfg).named_parameters())
    assert params["matchers.3.feature.first.linear.weight"].shape == (32, 1 + 64)  # [||d|| ; d/||d||]
    assert params["matchers.3.coord.first.linear.weight"].shape == (32, 1 + 3 + 3)  # plus p_S
    assert params["encoder.blocks.0.edge.linear.weight"].shape == (64, 3)
    assert params["encoder.blocks.4.point.weight"].shape == (64, 64)


def test_state_dict_keys_are_stable_for_checkpoints() -> None:
    """Checkpoints (and the ONNX export) depend on these names; renaming a module breaks them."""
    bn = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")

    def layer(prefix: str) -> list[str]:
        return [f"{prefix}.linear.weight", *(f"{prefix}.bn.{n}" for n in bn)]

    def pair(prefix: str) -> list[str]:
        return [*layer(f"{prefix}.first"), *layer(f"{prefix}.hidden.0"), *layer(f"{prefix}.hidden.1"),
                f"{prefix}.out.weight", f"{prefix}.out.bias"]

    expected = [
        *layer("encoder.blocks.0.edge"),
        "encoder.blocks.0.edge_out.weight", "encoder.blocks.0.edge_out.bias",
        "encoder.blocks.0.point.weight", "encoder.blocks.0.point.bias",
        *layer("significance.layers.0"), *layer("significance.layers.1"),
        "significance.layers.2.weight", "significance.layers.2.bias",
        *pair("matchers.0.feature"), *pair("matchers.0.coord"),
        "matchers.0.credibility.pre.weight", "matchers.0.credibility.pre.bias",
        *layer("matchers.0.credibility.post.0"),
        "matchers.0.credibility.post.1.weight", "matchers.0.credibility.post.1.bias",
    ]
    keys = list(MFGNet(MFGNetConfig(iterations=1, encoder_blocks=1)).state_dict())
    assert keys == expected


# --- helpers --------------------------------------------------------------------------------------


def test_knn_indices_are_the_k_nearest_points_including_the_point_itself() -> None:
    points = clouds(2, 50, 3, torch.float64)
    idx = knn_indices(points, 6)  # [B, N, k]
    assert idx.shape == (2, 50, 6)
    brute = torch.cdist(points, points).argsort(dim=-1)[..., :6]
    assert torch.equal(idx.sort(dim=-1).values, brute.sort(dim=-1).values)
    assert torch.equal(idx[..., 0], torch.arange(50).expand(2, 50))


def test_gather_points_indexes_each_batch_separately() -> None:
    values = torch.randn(3, 10, 4)
    idx = torch.randint(0, 10, (3, 5, 2))
    expected = torch.stack([values[b][idx[b]] for b in range(3)])
    assert torch.equal(gather_points(values, idx), expected)


def test_median_threshold_keeps_credibilities_at_or_above_the_lower_median() -> None:
    c = torch.tensor([[0.4, 0.1, 0.3, 0.2], [0.9, 0.5, 0.7, 0.8]])
    expected = torch.tensor([[0.4, 0.0, 0.3, 0.2], [0.9, 0.0, 0.7, 0.8]])
    assert torch.equal(median_threshold_weights(c), expected)
    c_odd = torch.tensor([[0.5, 0.1, 0.3]])
    assert torch.equal(median_threshold_weights(c_odd), torch.tensor([[0.5, 0.0, 0.3]]))


# --- rewrite 2: pair MLP without the [B, K, L, 1 + d + e] tensor ----------------------------------


def naive_pair_mlp(mlp: PairMLP, a: torch.Tensor, b: torch.Tensor, extra_a: torch.Tensor | None):
    """The paper's tensor ``[||a - b|| ; (a - b) / ||a - b|| ; extra_a]`` for every pair, then the MLP."""
    d = a[:, :, None] - b[:, None]  # [B, K, L, d]
    n = d.norm(dim=-1, keepdim=True)  # [B, K, L, 1]
    parts = [n, d / (n + NORM_EPS)]
    if extra_a is not None:
        parts.append(extra_a[:, :, None].expand(-1, -1, b.shape[1], -1))
    x = torch.cat(parts, dim=-1)  # [B, K, L, 1 + d + e]
    assert x.shape[-1] == mlp.first.linear.in_features
    z = bn_relu_linear(mlp.first, x)
    for layer in mlp.hidden:
        z = bn_relu_linear(layer, z)
    return mlp.out(z).squeeze(-1)  # [B, K, L]


@pytest.mark.parametrize("mode", ["eval", "train"])
@pytest.mark.parametrize(("diff_dims", "extra_dims"), [(64, 0), (3, 3)])
def test_pair_mlp_equals_the_naive_pair_tensor_mlp(mode: str, diff_dims: int, extra_dims: int) -> None:
    torch.manual_seed(0)
    mlp = randomise_batchnorm(PairMLP(diff_dims, extra_dims, 32)).double().train(mode == "train")
    g = torch.Generator().manual_seed(1)
    a = torch.randn(2, 12, diff_dims, generator=g, dtype=torch.float64)
    b = torch.randn(2, 9, diff_dims, generator=g, dtype=torch.float64)
    b[:, 0] = a[:, 0]  # a zero difference: ||d|| = 0 and d / (||d|| + eps) = 0
    extra = torch.randn(2, 12, extra_dims, generator=g, dtype=torch.float64) if extra_dims else None
    fast = mlp(a, b, extra)
    naive = naive_pair_mlp(copy.deepcopy(mlp), a, b, extra)
    assert fast.shape == (2, 12, 9)
    torch.testing.assert_close(fast, naive, rtol=1e-10, atol=1e-10)


# --- rewrite 1: edge convolution without the edge tensor ------------------------------------------


def naive_edge_conv(block: EdgeConvBlock, x: torch.Tensor, idx_nk: torch.Tensor) -> torch.Tensor:
    """``max_j point(edge_out(relu(bn(W (x_j - x_i)))))`` with the ``[B, N, k, C_in]`` edge tensor built."""
    x_j = torch.stack([x[b][idx_nk[b]] for b in range(x.shape[0])])  # [B, N, k, C_in]
    edges = x_j - x[:, :, None]  # [B, N, k, C_in]
    h = block.edge_out(bn_relu_linear(block.edge, edges))  # [B, N, k, C]
    return block.point(h.max(dim=2).values)  # [B, N, C]


@pytest.mark.parametrize("mode", ["eval", "train"])
@pytest.mark.parametrize("in_ch", [3, 16])
def test_edge_conv_equals_the_naive_edge_tensor_version(mode: str, in_ch: int) -> None:
    torch.manual_seed(0)
    block = randomise_batchnorm(EdgeConvBlock(in_ch, 16)).double().train(mode == "train")
    points = clouds(2, 40, 2, torch.float64)
    x = points if in_ch == 3 else torch.randn(2, 40, in_ch, dtype=torch.float64)
    idx_nk = knn_indices(points, 7)  # [B, N, k]
    fast = block(x, idx_nk.transpose(1, 2))  # the block takes k-major indices [B, k, N]
    naive = naive_edge_conv(copy.deepcopy(block), x, idx_nk)
    assert fast.shape == (2, 40, 16)
    torch.testing.assert_close(fast, naive, rtol=1e-10, atol=1e-10)


def test_encoder_equals_naive_edge_convolutions_on_one_xyz_graph() -> None:
    torch.manual_seed(0)
    cfg = MFGNetConfig(emb_dims=16, encoder_blocks=3, knn=5)
    encoder = randomise_batchnorm(Encoder(cfg)).double().eval()
    points = clouds(2, 30, 4, torch.float64)
    idx_nk = knn_indices(points, 5)  # the graph is built once, on the input xyz
    x = points
    for block in encoder.blocks:
        x = naive_edge_conv(block, x, idx_nk)
    torch.testing.assert_close(encoder(points), x, rtol=1e-10, atol=1e-10)


def test_credibility_head_equals_conv_on_stacked_matrices_then_max() -> None:
    torch.manual_seed(0)
    head = randomise_batchnorm(CredibilityHead(8)).double().eval()
    F_mat = torch.randn(2, 6, 5, dtype=torch.float64)
    S_mat = torch.randn(2, 6, 5, dtype=torch.float64)
    h = head.pre(torch.stack([F_mat, S_mat], dim=-1)).max(dim=2).values  # 1x1 conv, max over targets
    naive = head.post[1](bn_relu_linear(head.post[0], h)).squeeze(-1)
    torch.testing.assert_close(head(F_mat, S_mat), naive, rtol=1e-12, atol=1e-12)


# --- feature difference direction -----------------------------------------------------------------


@torch.no_grad()
def test_target_minus_source_equals_source_minus_target_with_negated_difference_weights() -> None:
    torch.manual_seed(0)
    cfg = MFGNetConfig(keypoints=24, emb_dims=16, encoder_blocks=2)
    a = randomise_batchnorm(MFGNet(cfg)).double().eval()
    b = MFGNet(MFGNetConfig(**{**cfg.to_dict(), "feature_diff": "target_minus_source"})).double().eval()
    b.load_state_dict(a.state_dict())
    src, tgt = clouds(2, 96, 0, torch.float64), clouds(2, 96, 1, torch.float64)
    out_a = a(src, tgt)
    out_b_unchanged = b(src, tgt)
    assert not torch.allclose(out_a.steps[0].scores, out_b_unchanged.steps[0].scores)
    for m in b.matchers:
        m.feature.first.linear.weight[:, 1:] *= -1  # the unit-difference weights; ||d|| is symmetric
    out_b = b(src, tgt)
    for step_a, step_b in zip(out_a.steps, out_b.steps, strict=True):
        torch.testing.assert_close(step_a.scores, step_b.scores, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(step_a.cred_logit, step_b.cred_logit, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out_a.rotation, out_b.rotation)
