"""Checkpoint -> ONNX graphs (encoder; one matcher graph per weight set) + ``manifest.json``.

The exported form is lean: BatchNorm is folded into the preceding linear layer (eval mode), and
the network's exact algebraic rewrites (per-point first layers) are what gets traced.
"""

from __future__ import annotations

import copy
import json
import time
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
import torch.nn.functional as F
from torch import nn

from model.network import (
    NORM_EPS,
    BNReLULinear,
    EdgeConvBlock,
    IterationMatcher,
    MFGNet,
    PairMLP,
    gather_points,
    knn_indices,
    pair_distance,
)

OPSET = 17
ENCODER_FILE = "encoder.onnx"
MATCHER_FILE = "matcher_{i}.onnx"


def _const(t: torch.Tensor) -> torch.Tensor:
    return t.detach().clone()


class AddShift(nn.Module):
    """What a BatchNorm becomes once its scale is folded into the previous linear layer."""

    def __init__(self, shift: torch.Tensor):
        super().__init__()
        self.register_buffer("shift", shift)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.shift


def fold_batchnorm(model: MFGNet) -> MFGNet:
    """Eval-mode copy with every ``BN(W x)`` folded into ``(a W) x + shift`` (exact)."""
    folded = copy.deepcopy(model).eval()
    for module in folded.modules():
        if isinstance(module, BNReLULinear) and isinstance(module.bn, nn.BatchNorm1d):
            bn = module.bn
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)  # [C]
            with torch.no_grad():
                module.linear.weight.mul_(scale[:, None])
            module.bn = AddShift((bn.bias - bn.running_mean * scale).detach())
    return folded


class LeanEdgeConv(nn.Module):
    """Export form of a folded ``EdgeConvBlock``: the BatchNorm shift is subtracted from the
    per-point centre term, ``relu(W x_j - (W x_i - shift))``, so the ``[B, k, N, C]`` edge tensor
    sees one Sub and one Relu instead of Sub, Add and Relu."""

    def __init__(self, block: EdgeConvBlock):
        super().__init__()
        self.linear = copy.deepcopy(block.edge.linear)
        self.register_buffer("shift", _const(block.edge.bn.shift))  # [C]
        self.register_buffer("edge_weight", _const(block.edge_out.weight))  # [C, C]
        self.register_buffer("edge_bias", _const(block.edge_out.bias))  # [C]
        self.point = copy.deepcopy(block.point)

    def forward(self, x: torch.Tensor, idx_kn: torch.Tensor) -> torch.Tensor:
        y = self.linear(x)  # [B, N, C]
        e = F.relu(gather_points(y, idx_kn) - (y - self.shift)[:, None])  # [B, k, N, C]
        e = F.linear(e, self.edge_weight).amax(dim=1) + self.edge_bias  # [B, N, C]
        return self.point(e)


class EncoderGraph(nn.Module):
    """``points [B, N, 3]``, ``neighbours [B, N, k]`` -> ``embedding [B, N, D]``, ``score [B, N]``.

    The k-NN graph is an input: the runtime builds it with a KD-tree (``service.neighbours``), far
    cheaper than an ``[N, N]`` distance matrix and TopK inside the graph.
    """

    def __init__(self, model: MFGNet):
        super().__init__()
        self.blocks = nn.ModuleList(LeanEdgeConv(block) for block in model.encoder.blocks)
        self.significance = copy.deepcopy(model.significance)

    def forward(self, points: torch.Tensor, neighbours: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        idx_kn = neighbours.transpose(1, 2)  # [B, k, N]
        x = points
        for block in self.blocks:
            x = block(x, idx_kn)
        return x, self.significance(x)  # [B, N, D], [B, N]


class LeanPairMLP(nn.Module):
    """Export form of a folded ``PairMLP``: the same arithmetic up to float rounding, with the pair
    tensor flattened to ``[B*K*L, C]`` so every hidden layer is one ``Gemm`` (bias = folded BatchNorm
    shift) that ONNX Runtime fuses with its ``Relu``."""

    def __init__(self, mlp: PairMLP):
        super().__init__()
        d = mlp.diff_dims
        W = mlp.first.linear.weight
        self.register_buffer("w_norm", _const(W[:, 0]))  # [C]
        self.register_buffer("W_diff", _const(W[:, 1 : 1 + d]))  # [C, d]
        self.register_buffer("W_extra", _const(W[:, 1 + d :]))  # [C, e]
        self.register_buffer("shift", _const(mlp.first.bn.shift))  # [C]
        self.hidden = nn.ModuleList()
        for layer in mlp.hidden:
            lin = nn.Linear(layer.linear.in_features, layer.linear.out_features)
            lin.weight.data, lin.bias.data = _const(layer.linear.weight), _const(layer.bn.shift)
            self.hidden.append(lin)
        self.out = copy.deepcopy(mlp.out)

    def forward(self, a: torch.Tensor, b: torch.Tensor, extra_a: torch.Tensor | None = None,
                dist: torch.Tensor | None = None) -> torch.Tensor:
        """``dist [B, K, L]``: ``||a - b||`` when the caller has it (else computed here)."""
        B, K, L = a.shape[0], a.shape[1], b.shape[1]
        dist = pair_distance(a, b) if dist is None else dist  # [B, K, L]
        inv = 1.0 / (dist + NORM_EPS)
        pa, pb = F.linear(a, self.W_diff), F.linear(b, self.W_diff)  # [B, K, C], [B, L, C]
        per_a = self.shift.expand(B, K, -1) if extra_a is None else F.linear(extra_a, self.W_extra) + self.shift
        # z = inv (pa_i - pb_j) + dist w_norm + per_a_i: the per-pair terms [inv, dist, 1] times a per-keypoint
        # [3, C] matrix in one batched MatMul, then the pb_j term: three [B, K, L, C] ops instead of five.
        coeff = torch.stack([pa, self.w_norm.expand(B, K, -1), per_a], dim=2)  # [B, K, 3, C]
        pair = torch.stack([inv, dist, torch.ones_like(dist)], dim=-1)  # [B, K, L, 3]
        z = F.relu(pair @ coeff - inv[..., None] * pb[:, None])  # [B, K, L, C]
        z = z.reshape(-1, z.shape[-1])  # [B*K*L, C]
        for layer in self.hidden:
            z = F.relu(layer(z))
        return self.out(z).reshape(B, K, L)


class MatcherGraph(nn.Module):
    """One iteration: keypoints, embeddings and their distances -> ``scores [B, K, L]``, ``cred_logit [B, K]``.

    ``emb_dist [B, K, L]`` (``||src_emb - tgt_emb||``) is an input: it is the same in every iteration,
    so the runtime computes it once per registration (``service.registrar.embedding_distance``)
    instead of each matcher call.
    """

    def __init__(self, model: MFGNet, index: int):
        super().__init__()
        matcher: IterationMatcher = model.matchers[index]
        self.feature, self.coord = LeanPairMLP(matcher.feature), LeanPairMLP(matcher.coord)
        self.sign, self.clamp = matcher.feature_sign, matcher.clamp
        cred = matcher.credibility
        self.register_buffer("pre_weight_t", _const(cred.pre.weight.t()))  # [2, C]
        self.register_buffer("pre_bias", _const(cred.pre.bias))
        post = nn.Linear(cred.post[0].linear.in_features, cred.post[0].linear.out_features)
        post.weight.data, post.bias.data = _const(cred.post[0].linear.weight), _const(cred.post[0].bn.shift)
        self.post, self.logit = post, copy.deepcopy(cred.post[1])

    def forward(self, src_xyz: torch.Tensor, tgt_xyz: torch.Tensor, src_emb: torch.Tensor, tgt_emb: torch.Tensor,
                emb_dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        F_mat = self.feature(self.sign * src_emb, self.sign * tgt_emb, dist=emb_dist)  # [B, K, L]
        S_mat = self.coord(src_xyz, tgt_xyz, src_xyz)  # [B, K, L]
        scores = (F_mat + S_mat).clamp(-self.clamp, self.clamp)
        h = torch.stack([F_mat, S_mat], dim=-1) @ self.pre_weight_t  # [B, K, L, C]
        h = h.amax(dim=2) + self.pre_bias  # [B, K, C]
        return scores, self.logit(F.relu(self.post(h))).squeeze(-1)


def _export(module: nn.Module, args: tuple, path: Path, inputs: list[str], outputs: list[str],
            dynamic: dict[str, dict[int, str]]) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, str(path), input_names=inputs, output_names=outputs,
                          dynamic_axes=dynamic, opset_version=OPSET, dynamo=False, do_constant_folding=True)
    graph = onnx.load(str(path))
    onnx.checker.check_model(graph, full_check=True)
    onnx.save(onnx.shape_inference.infer_shapes(graph, strict_mode=True), str(path))


def export_graphs(model: MFGNet, out_dir: Path) -> dict[str, str]:
    """Write the encoder and matcher graphs of ``model`` into ``out_dir``; returns role -> file."""
    out_dir.mkdir(parents=True, exist_ok=True)
    folded = fold_batchnorm(model)
    D = folded.cfg.emb_dims
    files = {"encoder": ENCODER_FILE}
    points = torch.rand(1, 64, 3)
    _export(EncoderGraph(folded), (points, knn_indices(points, folded.cfg.knn)), out_dir / ENCODER_FILE,
            ["points", "neighbours"], ["embedding", "score"],
            {"points": {0: "B", 1: "N"}, "neighbours": {0: "B", 1: "N"}, "embedding": {0: "B", 1: "N"},
             "score": {0: "B", 1: "N"}})
    src_emb, tgt_emb = torch.randn(1, 16, D), torch.randn(1, 20, D)
    example = (torch.rand(1, 16, 3), torch.rand(1, 20, 3), src_emb, tgt_emb, pair_distance(src_emb, tgt_emb))
    for i in range(len(folded.matchers)):
        name = MATCHER_FILE.format(i=i)
        _export(MatcherGraph(folded, i), example, out_dir / name,
                ["src_xyz", "tgt_xyz", "src_emb", "tgt_emb", "emb_dist"], ["scores", "cred_logit"],
                {"src_xyz": {0: "B", 1: "K"}, "tgt_xyz": {0: "B", 1: "L"}, "src_emb": {0: "B", 1: "K"},
                 "tgt_emb": {0: "B", 1: "L"}, "emb_dist": {0: "B", 1: "K", 2: "L"},
                 "scores": {0: "B", 1: "K", 2: "L"}, "cred_logit": {0: "B", 1: "K"}})
        files[f"matcher_{i}"] = name
    return files


def reference_radius(setting: str = "clean", count: int = 512, seed: int = 0, data: str | None = None) -> float:
    """Median robust radius of training-protocol source clouds (the ModelNet40 folder ``data``, default
    :func:`model.data.data_dir`'s): the runtime scales inputs to it."""
    from model.data import load_shapes, make_pairs, protocol_for
    from service.normalization import rms_radius

    shapes, _ = load_shapes("train", setting, data)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(shapes), size=min(count, len(shapes)), replace=False)
    pairs = make_pairs(shapes[pick], protocol_for(setting), rng)
    return float(np.median([rms_radius(src) for src in pairs["source"]]))


def search_section(protocol: dict | None, recipe: str | None = None) -> dict | None:
    """The manifest's ``search`` section for a checkpoint trained with ``protocol`` (its pair protocol as saved) or a
    ``recipe`` (whose pairs are independently sampled whatever ``--setting`` validated on): a subsample for models
    trained on independently sampled pairs, none (full clouds) for shared points."""
    from service.rotation_search import SEARCH_KEYPOINTS, SEARCH_POINTS

    if recipe is None and (protocol or {}).get("sampling", "shared") == "shared":
        return None
    return {"points": SEARCH_POINTS, "keypoints": SEARCH_KEYPOINTS}


def write_model_folder(out_dir: Path, checkpoint_path: Path, model: MFGNet, checkpoint: dict, setting: str,
                       version: str, accuracy: dict | None, data: str | None = None) -> None:
    """A servable model folder from ``model`` (loaded from ``checkpoint_path``, whose contents are ``checkpoint``):
    the graphs and the manifest, with the reference radius of ``setting`` (its shapes in the ModelNet40 folder
    ``data``) and the checkpoint's training provenance
    (``mfgnet train`` records it; none in checkpoints written before it did, or not by a run). No parity check."""
    from model.checkpoint import file_sha256

    files = export_graphs(model, out_dir)
    write_manifest(out_dir, out_dir.name, model, files, file_sha256(checkpoint_path), accuracy,
                   reference_radius(setting, data=data), version, source=checkpoint_path.name,
                   search=search_section(checkpoint.get("protocol"), trained_recipe(checkpoint)),
                   training=training_section(checkpoint))


def trained_recipe(checkpoint: dict) -> str | None:
    """The ``--recipe`` the checkpoint's run trained with, as its ``provenance`` records it (``None``: none, or no
    record)."""
    run = (checkpoint.get("provenance") or {}).get("run") if isinstance(checkpoint.get("provenance"), dict) else None
    options = run.get("options") if isinstance(run, dict) else None
    recipe = options.get("recipe") if isinstance(options, dict) else None
    return recipe if isinstance(recipe, str) else None


def training_section(checkpoint: dict) -> dict | None:
    """The manifest's optional ``training``: what made the checkpoint's run (its ``provenance``: the start's commit,
    data file, command line, options and versions, and each resume's), or ``None`` where it records none."""
    made_by = checkpoint.get("provenance")
    return made_by if isinstance(made_by, dict) else None


def write_manifest(out_dir: Path, name: str, model: MFGNet, files: dict[str, str], checkpoint_sha256: str,
                   accuracy: dict | None, radius: float, version: str, source: str, search: dict | None = None,
                   training: dict | None = None) -> Path:
    """``manifest.json``: name, version, config, opset, graph hashes, source hash, accuracy, and, when there are, the
    rotation search's subsample (``search``, :func:`search_section`) and what trained the checkpoint (``training``,
    :func:`training_section`)."""
    from model.checkpoint import file_sha256

    manifest = {
        "name": name,
        "version": version,
        "format": 1,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "source": source,
        "source_checkpoint_sha256": checkpoint_sha256,
        "config": model.cfg.to_dict(),
        "opset": OPSET,
        "graphs": {role: {"file": f, "sha256": file_sha256(out_dir / f)} for role, f in files.items()},
        "normalization": {"center": "per_cloud_centroid", "scale": "rms_radius", "reference_radius": radius},
        "accuracy": accuracy or {},
    }
    if search:
        manifest["search"] = search
    if training:
        manifest["training"] = training
    path = out_dir / "manifest.json"
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    return path
