"""A tiny network and training split for training tests that must run in seconds (no dataset needed).

Import as ``from tiny_training import ...`` (``tests/helpers`` is on ``sys.path``; see ``shapes.py``).
"""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from shapes import sphere_shapes

TINY_MODEL = {"iterations": 1, "keypoints": 32, "emb_dims": 8, "encoder_blocks": 1, "matcher_channels": 8,
              "knn": 8, "train_positives": 16, "train_negatives": 16}


def tiny_training_data(tmp_path) -> str:
    """A data folder whose training split is 30 random spheres (labels 0-19)."""
    folder = tmp_path / "data"
    folder.mkdir()
    np.savez(folder / "modelnet40_train.npz", points=sphere_shapes(30, seed=3).astype(np.float16),
             labels=np.arange(30) % 20)
    return str(folder)


def save_tiny_checkpoint(path) -> None:
    """A seeded, untrained 2-iteration network at ``path`` (for commands that read a checkpoint)."""
    import torch

    from model.checkpoint import save_checkpoint
    from model.config import MFGNetConfig
    from model.network import MFGNet

    torch.manual_seed(0)
    cfg = MFGNetConfig(iterations=2, keypoints=32, emb_dims=16, encoder_blocks=2, matcher_channels=8, knn=8)
    save_checkpoint(path, MFGNet(cfg))


@pytest.fixture
def tiny_checkpoint(tmp_path):
    """A tiny checkpoint (:func:`save_tiny_checkpoint`) in the test's folder; test modules import the fixture."""
    path = tmp_path / "tiny.pt"
    save_tiny_checkpoint(path)
    return path


def sigterm_in_step(monkeypatch, step: int) -> None:
    """Send this process SIGTERM (as ``kill`` would) during training step number ``step`` (from 1) of
    ``model.train``: a stop at a known batch."""
    import model.train

    steps = 0
    losses = model.train.registration_losses

    def counted(*args, **kwargs):
        nonlocal steps
        steps += 1
        if steps == step:
            os.kill(os.getpid(), signal.SIGTERM)
        return losses(*args, **kwargs)

    monkeypatch.setattr(model.train, "registration_losses", counted)
