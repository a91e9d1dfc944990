"""Training losses of the paper and the 64 positive + 64 negative keypoint sampling."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from model.network import RegistrationOutput, gather_points
from model.pose import transform_points


@dataclass
class LossTerms:
    keypoint: torch.Tensor
    matching: torch.Tensor
    credibility: torch.Tensor

    @property
    def total(self) -> torch.Tensor:
        return self.keypoint + self.matching + self.credibility


def keypoint_loss(significance: torch.Tensor, scores: torch.Tensor) -> torch.Tensor:
    """Mutual supervision: ``mean_i (s(i) - sum_j M log M)^2`` with ``M = softmax_j(scores)``.

    ``significance [B, K]`` of the source keypoints; ``scores [B, K, L]``. The entropy target is
    detached (it supervises the significance head only).
    """
    log_m = F.log_softmax(scores, dim=-1)  # [B, K, L]
    neg_entropy = (log_m.exp() * log_m).sum(-1)  # [B, K]
    return F.mse_loss(significance, neg_entropy.detach())


def matching_loss(scores: torch.Tensor, gt_index: torch.Tensor, has_partner: torch.Tensor) -> torch.Tensor:
    """``mean_i -y_i log softmax(M)(i, j*)``; ``gt_index [B, K]``, ``has_partner [B, K]`` bool."""
    log_m = F.log_softmax(scores, dim=-1)  # [B, K, L]
    nll = -log_m.gather(-1, gt_index[..., None]).squeeze(-1)  # [B, K]
    return (nll * has_partner).mean()


def credibility_loss(logit: torch.Tensor, correct: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy of the credibility ``[B, K]`` against correct-correspondence labels."""
    return F.binary_cross_entropy_with_logits(logit, correct.to(logit.dtype))


def ground_truth_matches(src_kp: torch.Tensor, tgt_kp: torch.Tensor, R_gt: torch.Tensor, t_gt: torch.Tensor,
                         threshold: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest target keypoint of each source keypoint under the true pose and whether it is close.

    ``src_kp [B, K, 3]`` (original source frame), ``tgt_kp [B, L, 3]`` -> ``[B, K]`` index, bool,
    and the source keypoints moved by the true pose ``[B, K, 3]``.
    """
    src_gt = transform_points(src_kp, R_gt, t_gt)  # [B, K, 3]
    dist, idx = torch.cdist(src_gt, tgt_kp).min(dim=-1)  # [B, K]
    return idx, dist < threshold, src_gt


def registration_losses(out: RegistrationOutput, src: torch.Tensor, tgt: torch.Tensor, R_gt: torch.Tensor,
                        t_gt: torch.Tensor, threshold: float) -> LossTerms:
    """Sum over iterations of matching and credibility losses plus the first-iteration keypoint loss."""
    src_kp, tgt_kp = gather_points(src, out.src_idx), gather_points(tgt, out.tgt_idx)
    gt_idx, has_partner, src_gt = ground_truth_matches(src_kp, tgt_kp, R_gt, t_gt, threshold)
    sig = out.src_scores.gather(1, out.src_idx)  # [B, K]
    kp = keypoint_loss(sig, out.steps[0].scores)
    match = torch.zeros((), dtype=src.dtype)
    cred = torch.zeros((), dtype=src.dtype)
    for step in out.steps:
        match = match + matching_loss(step.scores, gt_idx, has_partner)
        predicted = gather_points(tgt_kp, step.match)  # [B, K, 3]
        correct = (predicted - src_gt).norm(dim=-1) < threshold  # [B, K]
        cred = cred + credibility_loss(step.cred_logit, correct)
    return LossTerms(kp, match, cred)


def _pick(mask: torch.Tensor, count: int, generator: torch.Generator | None) -> torch.Tensor:
    """``count`` random indices per row where ``mask [B, N]`` is true, topped up from the rest."""
    key = torch.rand(mask.shape, generator=generator).to(mask.device) + 2.0 * mask  # [B, N]
    return key.topk(count, dim=-1).indices  # [B, count]


@torch.no_grad()
def sample_training_keypoints(src: torch.Tensor, tgt: torch.Tensor, R_gt: torch.Tensor, t_gt: torch.Tensor,
                              positives: int, negatives: int, threshold: float,
                              generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The paper's training keypoints: per cloud 64 points with a partner and 64 without.

    Source positives have a target point within ``threshold`` under the true pose; the target's
    positives are exactly those partners, so every positive has its match among the keypoints.
    Returns ``src_idx [B, P + Q]``, ``tgt_idx [B, P + Q]``.
    """
    for name, cloud in (("source", src), ("target", tgt)):
        if cloud.shape[1] < positives + negatives:
            raise ValueError(f"the {name} has {cloud.shape[1]} points; training samples {positives} + {negatives} "
                             "keypoints per cloud")
    src_gt = transform_points(src, R_gt, t_gt)  # [B, N, 3]
    dist = torch.cdist(src_gt, tgt)  # [B, N, M]
    nn_dist, nn_idx = dist.min(dim=-1)  # [B, N]
    src_has = nn_dist < threshold
    tgt_has = dist.min(dim=1).values < threshold  # [B, M]
    src_pos = _pick(src_has, positives, generator)
    src_neg = _pick(~src_has, negatives, generator)
    tgt_pos = nn_idx.gather(1, src_pos)  # partners of the source positives
    tgt_neg = _pick(~tgt_has, negatives, generator)
    return torch.cat([src_pos, src_neg], 1), torch.cat([tgt_pos, tgt_neg], 1)
