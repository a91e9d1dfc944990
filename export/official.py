"""Importer for the authors' released MFGNet checkpoints (``model_*.t7``, 215 tensors).

The released weights use 3 iterations with separate weights, K = 256, the feature difference
``e_t - e_s`` and unweighted centroids in the SVD (``model.config.OFFICIAL_CONFIG``). Never commit
the files or anything derived from them.
"""

from __future__ import annotations

import re

import torch

EXPECTED_KEYS = 215
REFLECT = torch.diag(torch.tensor([1.0, 1.0, -1.0]))
BN_FIELDS = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")

# official prefix pattern -> our prefix; "{b}" / "{i}" are filled from the match
_LAYER_MAP: list[tuple[str, str]] = [
    (r"emb_nn\.propogate(\d)\.conv2d\.conv\.0\.conv\.weight", "encoder.blocks.{b}.edge.linear.weight"),
    (r"emb_nn\.propogate(\d)\.conv2d\.conv\.0\.bn\.(\w+)", "encoder.blocks.{b}.edge.bn.{f}"),
    (r"emb_nn\.propogate(\d)\.conv2d\.conv\.1\.(weight|bias)", "encoder.blocks.{b}.edge_out.{f}"),
    (r"emb_nn\.propogate(\d)\.conv1d\.conv\.0\.(weight|bias)", "encoder.blocks.{b}.point.{f}"),
    (r"significance_fc\.conv\.([01])\.conv\.weight", "significance.layers.{i}.linear.weight"),
    (r"significance_fc\.conv\.([01])\.bn\.(\w+)", "significance.layers.{i}.bn.{f}"),
    (r"significance_fc\.conv\.2\.(weight|bias)", "significance.layers.2.{f}"),
    (r"sim_mat_([FS])conv\.(\d)\.conv\.([0-2])\.conv\.weight", "matchers.{i}.{m}.{layer}.linear.weight"),
    (r"sim_mat_([FS])conv\.(\d)\.conv\.([0-2])\.bn\.(\w+)", "matchers.{i}.{m}.{layer}.bn.{f}"),
    (r"sim_mat_([FS])conv\.(\d)\.conv\.3\.(weight|bias)", "matchers.{i}.{m}.out.{f}"),
    (r"preweight\.(\d)\.conv\.0\.(weight|bias)", "matchers.{i}.credibility.pre.{f}"),
    (r"weight_fc\.(\d)\.conv\.0\.conv\.weight", "matchers.{i}.credibility.post.0.linear.weight"),
    (r"weight_fc\.(\d)\.conv\.0\.bn\.(\w+)", "matchers.{i}.credibility.post.0.bn.{f}"),
    (r"weight_fc\.(\d)\.conv\.1\.(weight|bias)", "matchers.{i}.credibility.post.1.{f}"),
]
_MATCHER_LAYER = {"0": "first", "1": "hidden.0", "2": "hidden.1"}


def official_key_to_ours(key: str) -> str | None:
    """Our state-dict key of an official key (``None`` for the constant ``head.reflect``)."""
    if key == "head.reflect":
        return None
    for pattern, target in _LAYER_MAP:
        m = re.fullmatch(pattern, key)
        if not m:
            continue
        g = m.groups()
        if key.startswith("emb_nn"):
            return target.format(b=int(g[0]) - 1, f=g[1] if len(g) > 1 else "")
        if key.startswith("significance_fc"):
            return target.format(i=g[0], f=g[-1])
        if key.startswith("sim_mat"):
            module = "feature" if g[0] == "F" else "coord"
            layer = _MATCHER_LAYER.get(g[2], "")
            return target.format(m=module, i=g[1], layer=layer, f=g[-1])
        return target.format(i=g[0], f=g[-1])
    raise KeyError(f"unexpected key in the official checkpoint: {key}")


def convert_state_dict(official: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Map the authors' 215 tensors onto ``MFGNet`` (1x1 convolutions become linear layers)."""
    if len(official) != EXPECTED_KEYS:
        raise ValueError(f"expected {EXPECTED_KEYS} tensors in an official checkpoint, found {len(official)}")
    reflect = official.get("head.reflect")
    if reflect is None or reflect.shape != REFLECT.shape or not torch.allclose(reflect.float(), REFLECT):
        raise ValueError("head.reflect is missing or not diag(1, 1, -1)")
    ours = {}
    for key, value in official.items():
        name = official_key_to_ours(key)
        if name is None:
            continue
        if value.dim() >= 3:  # [out, in, 1(, 1)] convolution -> [out, in] linear
            value = value.reshape(value.shape[0], value.shape[1])
        ours[name] = value.clone()
    return ours
