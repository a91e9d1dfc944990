"""The paper's losses and the 64 + 64 training keypoint sampling of ``model.losses``, on hand-made cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from model.config import MFGNetConfig
from model.losses import (
    credibility_loss,
    ground_truth_matches,
    keypoint_loss,
    matching_loss,
    registration_losses,
    sample_training_keypoints,
)
from model.network import MFGNet, gather_points
from model.pose import transform_points

TH = 0.05


def log_softmax_at(row: list[float], j: int) -> float:
    return row[j] - math.log(sum(math.exp(v) for v in row))


# --- matching -------------------------------------------------------------------------------------


def test_matching_loss_is_masked_nll_of_the_softmax_averaged_over_all_keypoints() -> None:
    rows = [[[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], [[-1.0, 4.0, 0.5], [2.0, -3.0, 1.0]]]  # [B=2, K=2, L=3]
    gt = [[2, 0], [1, 2]]
    has = [[True, False], [True, True]]
    expected = sum(
        -log_softmax_at(rows[b][i], gt[b][i]) for b in range(2) for i in range(2) if has[b][i]
    ) / 4  # 1/K sum_i y_i (-log M(i, j*)): unmatched keypoints count in the mean with weight 0
    got = matching_loss(torch.tensor(rows, dtype=torch.float64), torch.tensor(gt), torch.tensor(has))
    assert float(got) == pytest.approx(expected, rel=1e-12)


def test_matching_loss_is_zero_without_partners() -> None:
    scores = torch.randn(2, 4, 5)
    got = matching_loss(scores, torch.zeros(2, 4, dtype=torch.long), torch.zeros(2, 4, dtype=torch.bool))
    assert float(got) == 0.0


def test_matching_loss_is_small_for_a_confident_correct_match() -> None:
    scores = torch.full((1, 3, 3), -20.0)
    scores[0, [0, 1, 2], [2, 0, 1]] = 20.0
    good = matching_loss(scores, torch.tensor([[2, 0, 1]]), torch.ones(1, 3, dtype=torch.bool))
    bad = matching_loss(scores, torch.tensor([[0, 1, 2]]), torch.ones(1, 3, dtype=torch.bool))
    assert float(good) < 1e-10
    assert float(bad) == pytest.approx(40.0, rel=1e-6)


# --- credibility ----------------------------------------------------------------------------------


def test_credibility_loss_is_binary_cross_entropy_of_the_sigmoid() -> None:
    logits = [[0.5, -1.0, 3.0], [0.0, 2.0, -2.5]]
    labels = [[True, False, False], [True, True, False]]

    def bce(x: float, y: bool) -> float:
        c = 1.0 / (1.0 + math.exp(-x))
        return -math.log(c) if y else -math.log(1.0 - c)

    expected = sum(bce(x, y) for lr, yr in zip(logits, labels, strict=True)
                   for x, y in zip(lr, yr, strict=True)) / 6
    got = credibility_loss(torch.tensor(logits, dtype=torch.float64), torch.tensor(labels))
    assert float(got) == pytest.approx(expected, rel=1e-12)


# --- keypoint (mutual supervision) ----------------------------------------------------------------


def negative_entropy(scores: torch.Tensor) -> torch.Tensor:
    """``sum_j M log M`` of ``M = softmax_j(scores)``, written out."""
    p = torch.exp(scores) / torch.exp(scores).sum(-1, keepdim=True)
    return (p * torch.log(p)).sum(-1)


def test_keypoint_loss_is_zero_when_significance_is_the_negative_entropy() -> None:
    scores = torch.randn(2, 5, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert float(keypoint_loss(negative_entropy(scores), scores)) == pytest.approx(0.0, abs=1e-24)


def test_keypoint_loss_is_the_mean_squared_distance_to_the_negative_entropy() -> None:
    scores = torch.randn(2, 5, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    offset = torch.linspace(-0.5, 0.5, 10, dtype=torch.float64).reshape(2, 5)
    loss = keypoint_loss(negative_entropy(scores) + offset, scores)
    assert float(loss) > 0
    assert float(loss) == pytest.approx(float((offset**2).mean()), rel=1e-10)


def test_keypoint_target_is_zero_for_a_confident_row_and_minus_log_l_for_a_uniform_one() -> None:
    scores = torch.tensor([[[50.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]]], dtype=torch.float64)
    significance = torch.tensor([[0.0, -math.log(4.0)]], dtype=torch.float64)
    assert float(keypoint_loss(significance, scores)) == pytest.approx(0.0, abs=1e-20)


def test_keypoint_loss_trains_only_the_significance() -> None:
    scores = torch.randn(1, 4, 4, requires_grad=True)
    significance = torch.zeros(1, 4, requires_grad=True)
    keypoint_loss(significance, scores).backward()
    assert scores.grad is None or float(scores.grad.abs().max()) == 0.0
    assert float(significance.grad.abs().max()) > 0.0


# --- ground truth ---------------------------------------------------------------------------------


def random_pose(seed: int, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    R = Rotation.random(batch, random_state=seed).as_matrix()
    t = rng.uniform(-0.5, 0.5, size=(batch, 3))
    return torch.from_numpy(R), torch.from_numpy(t)


def test_ground_truth_matches_finds_the_nearest_target_under_the_true_pose() -> None:
    R, t = random_pose(0)
    src = torch.tensor([[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]], dtype=torch.float64)
    moved = transform_points(src, R, t)  # [1, 4, 3]
    offsets = torch.tensor([[0.0, 0.0, 0.01], [0.03, 0.0, 0.0], [0.0, 0.049, 0.0], [0.0, 0.0, 0.2]],
                           dtype=torch.float64)
    tgt = (moved + offsets)[:, [2, 0, 3, 1]]  # shuffled: source i sits at target position perm^-1
    tgt = torch.cat([tgt, moved[:, :1] + 3.0], dim=1)  # plus a far outlier
    idx, has, src_gt = ground_truth_matches(src, tgt, R, t, TH)
    assert idx.tolist() == [[1, 3, 0, 2]]
    assert has.tolist() == [[True, True, True, False]]  # 0.2 is beyond the 0.05 threshold
    torch.testing.assert_close(src_gt, moved)


# --- training keypoints ---------------------------------------------------------------------------


def partial_pair(seed: int, batch: int = 2, shared: int = 160, src_only: int = 96, tgt_only: int = 96):
    """Source ``[B, shared + src_only, 3]`` and shuffled target ``[B, shared + tgt_only, 3]``: the first
    ``shared`` source points are in the target under the pose, the others on either side have no partner."""
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(batch, shared + src_only, 3, generator=g, dtype=torch.float64)
    src = src / src.norm(dim=-1, keepdim=True)  # on the unit sphere
    src[:, shared:] *= 3.0  # source-only points: away from every partner after the move
    R, t = random_pose(seed, batch)
    partners = transform_points(src[:, :shared], R, t)
    partners = partners + 0.002 * torch.randn(partners.shape, generator=g, dtype=torch.float64)
    outliers = 5.0 + torch.rand(batch, tgt_only, 3, generator=g, dtype=torch.float64)  # far from all
    tgt = torch.cat([partners, outliers], dim=1)
    perm = torch.randperm(tgt.shape[1], generator=g)
    return src, tgt[:, perm], R, t


def test_training_keypoints_are_64_positives_then_64_negatives_per_cloud() -> None:
    src, tgt, R, t = partial_pair(0)
    src_idx, tgt_idx = sample_training_keypoints(src, tgt, R, t, 64, 64, TH, torch.Generator().manual_seed(0))
    assert src_idx.shape == tgt_idx.shape == (2, 128)

    dist = torch.cdist(transform_points(src, R, t), tgt)  # [B, N, M]
    for b in range(2):
        s_pos, s_neg = src_idx[b, :64], src_idx[b, 64:]
        t_pos, t_neg = tgt_idx[b, :64], tgt_idx[b, 64:]
        assert len(set(s_pos.tolist())) == 64 and len(set(s_neg.tolist())) == 64
        assert len(set(t_neg.tolist())) == 64
        # source positives have a partner within the threshold, and the target positives are those partners
        assert (dist[b, s_pos].min(dim=-1).values < TH).all()
        assert t_pos.tolist() == dist[b, s_pos].argmin(dim=-1).tolist()
        assert (dist[b, s_pos, t_pos] < TH).all()
        # negatives have no partner at all
        assert (dist[b, s_neg].min(dim=-1).values >= TH).all()
        assert (dist[b][:, t_neg].min(dim=0).values >= TH).all()


def test_training_keypoints_need_positives_plus_negatives_points_per_cloud() -> None:
    src, tgt, R, t = partial_pair(0)
    with pytest.raises(ValueError, match="the target has 100 points; training samples 64 \\+ 64"):
        sample_training_keypoints(src, tgt[:, :100], R, t, 64, 64, TH)


def test_training_keypoints_are_seeded_and_random() -> None:
    src, tgt, R, t = partial_pair(1)
    a = sample_training_keypoints(src, tgt, R, t, 64, 64, TH, torch.Generator().manual_seed(5))
    b = sample_training_keypoints(src, tgt, R, t, 64, 64, TH, torch.Generator().manual_seed(5))
    c = sample_training_keypoints(src, tgt, R, t, 64, 64, TH, torch.Generator().manual_seed(6))
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not torch.equal(a[0], c[0])


def test_training_keypoints_top_up_with_other_points_when_negatives_are_scarce() -> None:
    src, tgt, R, t = partial_pair(2, shared=200, src_only=10, tgt_only=10)
    src_idx, tgt_idx = sample_training_keypoints(src, tgt, R, t, 64, 64, TH, torch.Generator().manual_seed(0))
    assert src_idx.shape == tgt_idx.shape == (2, 128)
    has = torch.cdist(transform_points(src, R, t), tgt).min(dim=-1).values < TH  # [B, N]
    for b in range(2):
        negatives = set(torch.nonzero(~has[b]).flatten().tolist())
        assert len(negatives) == 10
        assert negatives <= set(src_idx[b, 64:].tolist())  # every true negative is used


# --- the total ------------------------------------------------------------------------------------


def test_registration_losses_sum_matching_and_credibility_over_iterations_keypoint_once() -> None:
    torch.manual_seed(0)
    cfg = MFGNetConfig(iterations=3, emb_dims=8, encoder_blocks=1, matcher_channels=4, knn=4)
    model = MFGNet(cfg).double()
    src, tgt, R, t = partial_pair(3, shared=40, src_only=8, tgt_only=8)
    src_idx, tgt_idx = sample_training_keypoints(src, tgt, R, t, 8, 8, TH)
    out = model(src, tgt, src_idx=src_idx, tgt_idx=tgt_idx)
    terms = registration_losses(out, src, tgt, R, t, TH)

    src_kp, tgt_kp = gather_points(src, src_idx), gather_points(tgt, tgt_idx)
    gt_idx, has, src_gt = ground_truth_matches(src_kp, tgt_kp, R, t, TH)
    assert has[:, :8].all()  # positives have their partner among the target keypoints
    assert torch.equal(gt_idx[:, :8], torch.arange(8).expand(2, 8))
    expected_match = sum(matching_loss(s.scores, gt_idx, has) for s in out.steps)
    correct = [(gather_points(tgt_kp, s.match) - src_gt).norm(dim=-1) < TH for s in out.steps]
    expected_cred = sum(credibility_loss(s.cred_logit, c) for s, c in zip(out.steps, correct, strict=True))
    expected_kp = keypoint_loss(out.src_scores.gather(1, src_idx), out.steps[0].scores)
    torch.testing.assert_close(terms.matching, expected_match)
    torch.testing.assert_close(terms.credibility, expected_cred)
    torch.testing.assert_close(terms.keypoint, expected_kp)
    torch.testing.assert_close(terms.total, expected_match + expected_cred + expected_kp)
