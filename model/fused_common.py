"""Pieces shared by the fused training layers (``model.edge_fused``, ``model.pair_fused``)."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch import nn


def fused_training(module: nn.Module, x: torch.Tensor) -> bool:
    """Whether ``module`` (with a ``fused`` switch) takes its fused path for input ``x``: CPU training
    with gradients. Evaluation, ``no_grad`` and other devices run the eager layers."""
    return module.training and module.fused and x.device.type == "cpu" and torch.is_grad_enabled()


def fold_batch_statistics(
    bn: nn.BatchNorm1d, mean: torch.Tensor, var: torch.Tensor, count: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch statistics ``[C]`` (biased variance, over ``count`` samples) -> BatchNorm's ``scale, shift``
    (differentiable: ``BN(z) = z * scale + shift``); updates ``bn``'s running statistics as
    ``nn.BatchNorm1d`` does in training."""
    with torch.no_grad():
        momentum = bn.momentum if bn.momentum is not None else 1.0 / float(bn.num_batches_tracked + 1)
        bn.running_mean.lerp_(mean.detach(), momentum)
        bn.running_var.lerp_(var.detach() * count / (count - 1), momentum)
        bn.num_batches_tracked.add_(1)
    scale = bn.weight / torch.sqrt(var + bn.eps)  # [C]
    return scale, bn.bias - scale * mean


def max_gradient(
    values: torch.Tensor, maxima: torch.Tensor, grad_max: torch.Tensor, out: torch.Tensor | None = None
) -> torch.Tensor:
    """Gradient of ``amax(values, dim=1)`` -> ``values``: ``values [p, k, C]``, ``maxima`` and ``grad_max
    [p, C]``, written to ``out`` (default: over ``values``). Ties share the gradient equally, as
    ``torch.amax``'s backward does."""
    out = values if out is None else out
    is_max = torch.eq(values, maxima[:, None], out=out)  # 1.0 at the max (a float result: ~4x faster than bool)
    share = grad_max / is_max.sum(1).clamp_min_(1.0)  # [p, C]; >= 1 tie unless the max is NaN
    return is_max.mul_(share[:, None])


def chunks(n: int, size: int) -> Iterator[slice]:
    """Slices ``[0, size), [size, 2 size), ...`` covering ``range(n)``."""
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))
