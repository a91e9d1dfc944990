"""Batched PyTorch inference over a pairs dict (evaluation, validation, baselines)."""

from __future__ import annotations

import time

import numpy as np
import torch

from model.network import MFGNet


@torch.no_grad()
def predict_poses(model: MFGNet, pairs: dict[str, np.ndarray], batch_size: int = 16,
                  iterations: int | None = None, keypoints: int | None = None,
                  progress: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """``src_to_tgt`` poses ``R [M, 3, 3]``, ``t [M, 3]`` for every pair, and the seconds spent."""
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    M = len(pairs["source"])
    Rs, ts = [], []
    starts = range(0, M, batch_size)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, desc="evaluate", unit="batch")
    begin = time.perf_counter()
    for s in starts:
        src = torch.from_numpy(pairs["source"][s : s + batch_size]).to(device)
        tgt = torch.from_numpy(pairs["target"][s : s + batch_size]).to(device)
        out = model(src, tgt, iterations=iterations, keypoints=keypoints)
        Rs.append(out.rotation.cpu().numpy())
        ts.append(out.translation.cpu().numpy())
    seconds = time.perf_counter() - begin
    model.train(was_training)
    return np.concatenate(Rs), np.concatenate(ts), seconds
