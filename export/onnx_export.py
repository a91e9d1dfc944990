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
from torch import nn

from model.network import BNReLULinear, MFGNet

OPSET = 17
ENCODER_FILE = "encoder.onnx"
MATCHER_FILE = "matcher_{i}.onnx"


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


class EncoderGraph(nn.Module):
    """``points [B, N, 3]`` -> ``embedding [B, N, D]``, ``score [B, N]``."""

    def __init__(self, model: MFGNet):
        super().__init__()
        self.model = model

    def forward(self, points: torch.Tensor):
        return self.model.embed(points)


class MatcherGraph(nn.Module):
    """One iteration: keypoints + embeddings -> ``scores [B, K, L]``, ``cred_logit [B, K]``."""

    def __init__(self, model: MFGNet, index: int):
        super().__init__()
        self.matcher = model.matchers[index]

    def forward(self, src_xyz, tgt_xyz, src_emb, tgt_emb):
        return self.matcher(src_xyz, tgt_xyz, src_emb, tgt_emb)


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
    _export(EncoderGraph(folded), (torch.rand(1, 64, 3),), out_dir / ENCODER_FILE, ["points"],
            ["embedding", "score"], {"points": {0: "B", 1: "N"}, "embedding": {0: "B", 1: "N"},
                                     "score": {0: "B", 1: "N"}})
    example = (torch.rand(1, 16, 3), torch.rand(1, 20, 3), torch.randn(1, 16, D), torch.randn(1, 20, D))
    for i in range(len(folded.matchers)):
        name = MATCHER_FILE.format(i=i)
        _export(MatcherGraph(folded, i), example, out_dir / name,
                ["src_xyz", "tgt_xyz", "src_emb", "tgt_emb"], ["scores", "cred_logit"],
                {"src_xyz": {0: "B", 1: "K"}, "tgt_xyz": {0: "B", 1: "L"}, "src_emb": {0: "B", 1: "K"},
                 "tgt_emb": {0: "B", 1: "L"}, "scores": {0: "B", 1: "K", 2: "L"}, "cred_logit": {0: "B", 1: "K"}})
        files[f"matcher_{i}"] = name
    return files


def reference_radius(setting: str = "clean", count: int = 512, seed: int = 0) -> float:
    """Median robust radius of training-protocol source clouds: the runtime scales inputs to it."""
    from model.data import load_shapes, make_pairs, protocol_for
    from service.normalization import rms_radius

    shapes, _ = load_shapes("train", setting)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(shapes), size=min(count, len(shapes)), replace=False)
    pairs = make_pairs(shapes[pick], protocol_for(setting), rng)
    return float(np.median([rms_radius(src) for src in pairs["source"]]))


def write_manifest(out_dir: Path, name: str, model: MFGNet, files: dict[str, str], checkpoint_sha256: str,
                   accuracy: dict | None, radius: float, version: str, source: str) -> Path:
    """``manifest.json``: name, version, config, opset, graph hashes, source hash, accuracy."""
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
    path = out_dir / "manifest.json"
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    return path
