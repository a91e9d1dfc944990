"""MFGNet: GNN encoder, keypoint significance, feature/coordinate-guided matching, credibility.

Channels-last throughout (``[B, N, C]``, ``nn.Linear``) and two exact algebraic rewrites keep
training fast on a CPU:

* first edge-convolution layer: ``W (x_j - x_i) = W x_j - W x_i`` is computed per point and
  gathered, instead of building the ``[B, N, k, C_in]`` edge tensor;
* first matcher layer: ``W [n ; d / n]`` with ``d = a - b`` is ``w0 n + (W1 a - W1 b) / n``, so
  the ``[B, K, K, 65]`` feature tensor is never materialised, only its ``[B, K, K, 32]`` image.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from model.config import MFGNetConfig
from model.edge_fused import EdgeGraph, edge_graph, fused_edge_max
from model.fused_common import fused_training
from model.pair_fused import PairMax, fused_pair_mlp
from model.pose import compose, transform_points, weighted_procrustes
from service.neighbours import knn_graph

NORM_EPS = 1e-8  # the unit difference is d / (||d|| + NORM_EPS)


class BNReLULinear(nn.Module):
    """Linear (no bias) -> BatchNorm -> ReLU on the last dimension of any ``[..., C]`` tensor."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.linear = nn.Linear(in_ch, out_ch, bias=False)
        self.bn = nn.BatchNorm1d(out_ch)

    def norm_relu(self, x: torch.Tensor) -> torch.Tensor:
        """BatchNorm + ReLU of an already projected ``[..., C]`` tensor."""
        shape = x.shape
        return F.relu(self.bn(x.reshape(-1, shape[-1])).reshape(shape))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm_relu(self.linear(x))


def pair_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Exact Euclidean distances ``[B, K, L]`` between ``a [B, K, d]`` and ``b [B, L, d]``.

    ``torch.cdist`` (non-matmul mode) in PyTorch; explicit differences when exporting to ONNX, one
    coordinate at a time: ONNX Runtime broadcasts ``[B, K, 1] - [B, 1, L]`` in spans of ``L``, but
    ``[B, K, 1, 3] - [B, 1, L, 3]`` in spans of 3 (0.6 ms instead of ~0.05 for 128 x 128 pairs).
    """
    if torch.onnx.is_in_onnx_export():
        d2 = None
        for c in range(a.shape[-1]):
            diff = a[:, :, None, c] - b[:, None, :, c]  # [B, K, L]
            d2 = diff * diff if d2 is None else d2 + diff * diff  # Mul, not Pow: ONNX Runtime's Pow is ~2x slower
        return d2.sqrt()
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")


def knn_indices(points: torch.Tensor, k: int) -> torch.Tensor:
    """Indices ``[B, N, k]`` of the k nearest points of each point (itself included).

    Squared distances are summed per coordinate from explicit differences (no ``|a|^2 + |b|^2 -
    2ab`` cancellation), so PyTorch and ONNX Runtime compute bit-identical values and pick the
    same neighbours.
    """
    d2 = None
    for c in range(3):
        diff = points[:, :, None, c] - points[:, None, :, c]  # [B, N, N]
        d2 = diff * diff if d2 is None else d2 + diff * diff
    return d2.topk(k, dim=-1, largest=False).indices


def gather_points(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``values [B, N, C]`` gathered at ``idx [B, ...]`` -> ``[B, ..., C]``."""
    B, N, C = values.shape
    flat = idx.reshape(B, -1) + torch.arange(B, device=idx.device)[:, None] * N  # [B, M]
    return values.reshape(B * N, C).index_select(0, flat.reshape(-1)).reshape(*idx.shape, C)


class EdgeConvBlock(nn.Module):
    """Edge convolution: BN-ReLU on ``x_j - x_i``, linear, max over neighbours, linear."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.edge = BNReLULinear(in_ch, out_ch)
        self.edge_out = nn.Linear(out_ch, out_ch)
        self.point = nn.Linear(out_ch, out_ch)

    def forward(self, x: torch.Tensor, idx_kn: torch.Tensor, graph: EdgeGraph | None = None) -> torch.Tensor:
        """``x [B, N, C_in]``, neighbour indices ``idx_kn [B, k, N]`` (k-major: the max over
        neighbours is then an element-wise maximum of contiguous slabs) -> ``[B, N, C]``.

        ``graph`` (the same k-NN graph over the flattened batch) selects the fused training path
        (``model.edge_fused``: batch statistics, far less memory traffic).
        """
        y = self.edge.linear(x)  # [B, N, C] = W x, per point (rewrite 1)
        if graph is not None:
            B, N, C = y.shape
            e = fused_edge_max(y.reshape(B * N, C), graph, self.edge.bn, self.edge_out.weight)  # [B * N, C]
            return self.point(e.view(B, N, C) + self.edge_out.bias)
        e = gather_points(y, idx_kn) - y[:, None]  # [B, k, N, C] = W x_j - W x_i
        e = self.edge.norm_relu(e)
        # max(e W^T + b) = max(e W^T) + b: the bias is added after the max (exact).
        e = F.linear(e, self.edge_out.weight).max(dim=1).values + self.edge_out.bias  # [B, N, C]
        return self.point(e)  # [B, N, C]


class Encoder(nn.Module):
    """GNN encoder on a k-NN graph of the input xyz (computed once): ``[B, N, 3] -> [B, N, D]``."""

    def __init__(self, cfg: MFGNetConfig):
        super().__init__()
        chans = [3] + [cfg.emb_dims] * cfg.encoder_blocks
        self.blocks = nn.ModuleList(EdgeConvBlock(a, b) for a, b in itertools.pairwise(chans))
        self.k = cfg.knn
        self.fused = True  # CPU training uses model.edge_fused (same results, far less memory traffic)

    def forward(self, points: torch.Tensor, neighbours: torch.Tensor | None = None) -> torch.Tensor:
        """``neighbours [B, N, k]``: the k-NN graph when the caller has it (else computed here)."""
        fused = fused_training(self, points)
        if neighbours is not None:
            idx_nk = neighbours
        elif fused:  # the runtime's KD-tree: ~7x faster than the [N, N] distances + topk on a training batch
            idx_nk = torch.from_numpy(knn_graph(points.detach().numpy(), self.k))
        else:
            idx_nk = knn_indices(points, self.k)
        idx_kn = idx_nk.transpose(1, 2)  # [B, k, N]
        graph = None
        if fused:
            B, N, _ = points.shape
            nbr = (idx_nk + torch.arange(B, device=points.device)[:, None, None] * N).reshape(B * N, -1)
            graph = edge_graph(nbr, points.dtype)  # [B * N, k]
        x = points
        for block in self.blocks:
            x = block(x, idx_kn, graph)
        return x  # [B, N, D]


class SignificanceHead(nn.Module):
    """Keypoint significance score per point: ``[B, N, D] -> [B, N]``."""

    def __init__(self, cfg: MFGNetConfig):
        super().__init__()
        self.layers = nn.Sequential(BNReLULinear(cfg.emb_dims, 64), BNReLULinear(64, 32), nn.Linear(32, 1))

    def forward(self, emb: torch.Tensor) -> torch.Tensor:
        return self.layers(emb).squeeze(-1)


class PairMLP(nn.Module):
    """Matcher MLP over every (source a, target b) pair; the first layer is split per point.

    ``first`` maps ``[||d|| ; d / ||d|| ; extra_a]`` (``1 + dim + extra`` channels) to ``C``; it is
    evaluated as ``w0 ||d|| + (W_d a - W_d b) / (||d|| + eps) + W_e extra_a`` (rewrite 2).
    """

    def __init__(self, diff_dims: int, extra_dims: int, ch: int):
        super().__init__()
        self.diff_dims, self.extra_dims = diff_dims, extra_dims
        self.first = BNReLULinear(1 + diff_dims + extra_dims, ch)
        self.hidden = nn.Sequential(BNReLULinear(ch, ch), BNReLULinear(ch, ch))
        self.out = nn.Linear(ch, 1)
        self.fused = True  # CPU training uses model.pair_fused (same results, far fewer passes)

    def forward(
        self, a: torch.Tensor, b: torch.Tensor, extra_a: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``a [B, K, d]``, ``b [B, L, d]`` with pair difference ``a - b`` -> scores ``[B, K, L]``."""
        W = self.first.linear.weight  # [C, 1 + d + e]
        w_norm, W_d = W[:, 0], W[:, 1 : 1 + self.diff_dims]
        dist = pair_distance(a, b)  # [B, K, L]
        pa, pb = F.linear(a, W_d), F.linear(b, W_d)  # [B, K, C], [B, L, C]
        pa_extra = F.linear(extra_a, W[:, 1 + self.diff_dims :]) if extra_a is not None else None  # [B, K, C]
        inv = 1.0 / (dist + NORM_EPS)  # [B, K, L]
        if fused_training(self, a):
            return fused_pair_mlp(self, pa, pb, pa_extra, w_norm, inv, dist)  # [B, K, L]
        z = (pa[:, :, None] - pb[:, None]) * inv[..., None] + dist[..., None] * w_norm  # [B, K, L, C]
        if pa_extra is not None:
            z = z + pa_extra[:, :, None]
        z = self.hidden(self.first.norm_relu(z))
        return self.out(z).squeeze(-1)  # [B, K, L]


class CredibilityHead(nn.Module):
    """Credibility logit per source keypoint from the stacked ``[F, S]`` matrices."""

    def __init__(self, ch: int):
        super().__init__()
        self.pre = nn.Linear(2, ch)
        self.post = nn.Sequential(BNReLULinear(ch, ch), nn.Linear(ch, 1))
        self.fused = True  # CPU training uses model.pair_fused.PairMax (same results, less memory traffic)

    def forward(self, F_mat: torch.Tensor, S_mat: torch.Tensor) -> torch.Tensor:
        w = self.pre.weight  # [C, 2]
        # pre([F, S]) then max over b; the bias commutes with the max (exact).
        if fused_training(self, F_mat):
            h = PairMax.apply(F_mat, S_mat, w[:, 0], w[:, 1])  # [B, K, C]
        else:
            h = (F_mat[..., None] * w[:, 0] + S_mat[..., None] * w[:, 1]).max(dim=2).values  # [B, K, C]
        return self.post(h + self.pre.bias).squeeze(-1)  # [B, K]


class IterationMatcher(nn.Module):
    """One iteration's feature matcher (65 ch), coordinate matcher (7 ch) and credibility head."""

    def __init__(self, cfg: MFGNetConfig):
        super().__init__()
        ch = cfg.matcher_channels
        self.feature = PairMLP(cfg.emb_dims, 0, ch)
        self.coord = PairMLP(3, 3, ch)
        self.credibility = CredibilityHead(ch)
        self.clamp = cfg.clamp
        self.feature_sign = 1.0 if cfg.feature_diff == "source_minus_target" else -1.0

    def forward(self, src_xyz: torch.Tensor, tgt_xyz: torch.Tensor, src_emb: torch.Tensor,
                tgt_emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints ``[B, K, 3]``/``[B, L, 3]`` (source in its current frame) and embeddings.

        Returns the matching matrix ``clamp(F + S) [B, K, L]`` and credibility logits ``[B, K]``.
        """
        s = self.feature_sign
        F_mat = self.feature(s * src_emb, s * tgt_emb)  # [B, K, L]
        S_mat = self.coord(src_xyz, tgt_xyz, src_xyz)  # [B, K, L]
        scores = (F_mat + S_mat).clamp(-self.clamp, self.clamp)
        return scores, self.credibility(F_mat, S_mat)


def median_threshold_weights(credibility: torch.Tensor) -> torch.Tensor:
    """Keep credibilities at or above the (lower) median, zero the rest: ``[B, K] -> [B, K]``."""
    med = credibility.median(dim=-1, keepdim=True).values  # lower median, as numpy partition
    return credibility * (credibility >= med)


@dataclass
class IterationOutput:
    """What one iteration produced (all ``B``-batched)."""

    scores: torch.Tensor  # [B, K, L] clamped matching matrix
    cred_logit: torch.Tensor  # [B, K]
    match: torch.Tensor  # [B, K] index into the target keypoints
    weights: torch.Tensor  # [B, K] median-thresholded credibilities (unnormalised)
    rotation: torch.Tensor  # [B, 3, 3] this step's pose
    translation: torch.Tensor  # [B, 3]


@dataclass
class RegistrationOutput:
    rotation: torch.Tensor  # [B, 3, 3] total src_to_tgt
    translation: torch.Tensor  # [B, 3]
    src_idx: torch.Tensor  # [B, K] keypoint indices into the source
    tgt_idx: torch.Tensor  # [B, L] keypoint indices into the target
    src_scores: torch.Tensor  # [B, N] significance
    tgt_scores: torch.Tensor  # [B, M]
    steps: list[IterationOutput]


class MFGNet(nn.Module):
    """The whole network; ``forward`` runs the n-iteration registration loop."""

    def __init__(self, cfg: MFGNetConfig | None = None):
        super().__init__()
        self.cfg = cfg or MFGNetConfig()
        self.encoder = Encoder(self.cfg)
        self.significance = SignificanceHead(self.cfg)
        self.matchers = nn.ModuleList(IterationMatcher(self.cfg) for _ in range(self.cfg.weight_sets))

    def set_fused_training(self, enabled: bool) -> None:
        """Use (default) or bypass the fused CPU training layers (``model.edge_fused``, ``model.pair_fused``)."""
        for module in self.modules():
            if isinstance(module, Encoder | PairMLP | CredibilityHead):
                module.fused = enabled

    def matcher(self, iteration: int) -> IterationMatcher:
        """Weight set of an iteration; past the trained sets the last one is reused."""
        return self.matchers[min(iteration, len(self.matchers) - 1)]

    def embed(
        self, points: torch.Tensor, neighbours: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``[B, N, 3]`` (and optionally its k-NN graph ``[B, N, k]``) -> embeddings ``[B, N, D]``
        and significance scores ``[B, N]``."""
        emb = self.encoder(points, neighbours)
        return emb, self.significance(emb)

    def forward(
        self,
        src: torch.Tensor,
        tgt: torch.Tensor,
        iterations: int | None = None,
        keypoints: int | None = None,
        src_idx: torch.Tensor | None = None,
        tgt_idx: torch.Tensor | None = None,
    ) -> RegistrationOutput:
        """Register ``src [B, N, 3]`` to ``tgt [B, M, 3]``.

        Keypoints are the top-K by significance unless ``src_idx``/``tgt_idx`` (``[B, K]``) are
        given (training samples positives and negatives instead). The pose is detached between
        iterations: every loss is on correspondences, none back-propagates through the SVD.
        """
        n_iter = iterations or self.cfg.iterations
        K = keypoints or self.cfg.keypoints
        B = src.shape[0]
        emb_both, score_both = None, None
        if src.shape[1] == tgt.shape[1]:
            emb_both, score_both = self.embed(torch.cat([src, tgt], dim=0))  # one batched encoder pass
            src_emb, tgt_emb = emb_both[:B], emb_both[B:]
            src_score, tgt_score = score_both[:B], score_both[B:]
        else:
            (src_emb, src_score), (tgt_emb, tgt_score) = self.embed(src), self.embed(tgt)
        if src_idx is None:
            src_idx = src_score.topk(min(K, src.shape[1]), dim=-1).indices  # [B, K]
        if tgt_idx is None:
            tgt_idx = tgt_score.topk(min(K, tgt.shape[1]), dim=-1).indices  # [B, L]
        ps, pt = gather_points(src, src_idx), gather_points(tgt, tgt_idx)  # [B, K, 3], [B, L, 3]
        fs, ft = gather_points(src_emb, src_idx), gather_points(tgt_emb, tgt_idx)  # [B, K, D], [B, L, D]

        R_total = torch.eye(3, dtype=src.dtype, device=src.device).expand(B, 3, 3)
        t_total = torch.zeros(B, 3, dtype=src.dtype, device=src.device)
        steps: list[IterationOutput] = []
        ps_cur = ps
        for it in range(n_iter):
            scores, logit = self.matcher(it)(ps_cur, pt, fs, ft)
            match = scores.argmax(dim=-1)  # [B, K]
            weights = median_threshold_weights(torch.sigmoid(logit.detach()))
            R, t = weighted_procrustes(ps_cur.detach(), gather_points(pt, match), weights, self.cfg.centroid)
            ps_cur = transform_points(ps_cur.detach(), R, t)
            R_total, t_total = compose(R, t, R_total, t_total)
            steps.append(IterationOutput(scores, logit, match, weights, R, t))
        return RegistrationOutput(R_total, t_total, src_idx, tgt_idx, src_score, tgt_score, steps)
