"""ModelNet40 partial-overlap registration protocol (the paper's, vectorised) and pairs files.

Protocol (one pair per shape): 1024 points; ``R = Rx Ry Rz`` with each angle uniform in
``[0, max_angle]``; ``t`` uniform in ``[-0.5, 0.5]^3``; ``target = R source + t``; optional Gaussian
noise (sigma 0.01, clipped at +-0.05) added to each cloud independently, before the crop; both
clouds cropped to the ``keep`` points nearest to one far point ``U[0,1)^3 + 500 s (1,1,1)``,
``s = +-1``, the same point for both (applied after moving the target). Target points are
shuffled so that no index correspondence leaks.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DATA_ENV = "MFGNET_DATA"
DEFAULT_DATA_DIR = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "modelnet40"
SETTINGS = ("clean", "noise", "unseen")
UNSEEN_SPLIT_LABEL = 20  # "unseen": train on labels 0-19, test on 20-39


def data_dir(path: str | os.PathLike | None = None) -> Path:
    """ModelNet40 directory: explicit path, else ``$MFGNET_DATA``, else ``../shared/data/modelnet40``."""
    return Path(path or os.environ.get(DATA_ENV) or DEFAULT_DATA_DIR)


@dataclass(frozen=True)
class PairProtocol:
    """Parameters of pair generation (the paper's defaults)."""

    points: int = 1024
    keep: int = 768  # points kept by the crop (source and target)
    max_angle_deg: float = 45.0
    max_translation: float = 0.5
    noise_sigma: float = 0.0
    noise_clip: float = 0.05
    far_distance: float = 500.0


def protocol_for(setting: str) -> PairProtocol:
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}; expected one of {SETTINGS}")
    return PairProtocol(noise_sigma=0.01 if setting == "noise" else 0.0)


def load_shapes(split: str, setting: str = "clean", path=None) -> tuple[np.ndarray, np.ndarray]:
    """Points ``float32 [S, 1024, 3]`` and labels ``int64 [S]`` of a split, filtered for "unseen"."""
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    file = data_dir(path) / f"modelnet40_{split}.npz"
    if not file.exists():
        raise FileNotFoundError(f"ModelNet40 file not found: {file} (set --data or ${DATA_ENV})")
    with np.load(file) as d:
        points, labels = d["points"].astype(np.float32), d["labels"].astype(np.int64)
    if setting == "unseen":
        keep = labels < UNSEEN_SPLIT_LABEL if split == "train" else labels >= UNSEEN_SPLIT_LABEL
        points, labels = points[keep], labels[keep]
    return points, labels


def euler_xyz_to_matrix(angles: np.ndarray) -> np.ndarray:
    """``R = Rx(a) Ry(b) Rz(c)`` for ``angles [B, 3]`` in radians -> ``[B, 3, 3]``."""
    cx, cy, cz = np.cos(angles).T
    sx, sy, sz = np.sin(angles).T
    one, zero = np.ones_like(cx), np.zeros_like(cx)
    Rx = np.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).reshape(-1, 3, 3)
    Ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(-1, 3, 3)
    Rz = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    return Rx @ Ry @ Rz


def crop_nearest(points: np.ndarray, anchor: np.ndarray, keep: int) -> np.ndarray:
    """The ``keep`` points of ``points [B, N, 3]`` nearest to ``anchor [B, 3]`` -> ``[B, keep, 3]``."""
    d2 = ((points - anchor[:, None]) ** 2).sum(-1)  # [B, N]
    idx = np.argpartition(d2, keep - 1, axis=1)[:, :keep]  # [B, keep]
    idx.sort(axis=1)  # keep the stored point order (independent of partition internals)
    return np.take_along_axis(points, idx[..., None], axis=1)


def make_pairs(shapes: np.ndarray, protocol: PairProtocol, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One pair per shape of ``shapes [B, N, 3]``; returns source/target/rotation/translation."""
    B = shapes.shape[0]
    src = shapes[:, : protocol.points].astype(np.float64)  # [B, N, 3]
    angles = rng.uniform(0.0, np.deg2rad(protocol.max_angle_deg), size=(B, 3))
    R = euler_xyz_to_matrix(angles)  # [B, 3, 3]
    t = rng.uniform(-protocol.max_translation, protocol.max_translation, size=(B, 3))
    tgt = src @ R.transpose(0, 2, 1) + t[:, None]  # [B, N, 3]
    if protocol.noise_sigma > 0:
        clip = protocol.noise_clip
        src = src + np.clip(rng.normal(0, protocol.noise_sigma, src.shape), -clip, clip)
        tgt = tgt + np.clip(rng.normal(0, protocol.noise_sigma, tgt.shape), -clip, clip)
    sign = rng.choice([-1.0, 1.0], size=(B, 1))
    anchor = rng.uniform(0.0, 1.0, size=(B, 3)) + protocol.far_distance * sign  # [B, 3]
    src = crop_nearest(src, anchor, protocol.keep)
    tgt = crop_nearest(tgt, anchor, protocol.keep)
    perm = rng.permuted(np.tile(np.arange(protocol.keep), (B, 1)), axis=1)  # [B, keep]
    tgt = np.take_along_axis(tgt, perm[..., None], axis=1)
    return {
        "source": src.astype(np.float32),
        "target": tgt.astype(np.float32),
        "rotation": R.astype(np.float32),
        "translation": t.astype(np.float32),
    }


def make_test_pairs(setting: str, split: str = "test", count: int | None = None, seed: int = 0, path=None):
    """Deterministic pairs of a setting: the same seed gives the same pairs on every machine."""
    shapes, labels = load_shapes(split, setting, path)
    rng = np.random.default_rng(seed)
    if count is not None and count < len(shapes):
        pick = np.sort(rng.choice(len(shapes), size=count, replace=False))
        shapes, labels = shapes[pick], labels[pick]
    pairs = make_pairs(shapes, protocol_for(setting), rng)
    pairs["label"] = labels
    return pairs


PAIR_KEYS = ("source", "target", "rotation", "translation")


def save_pairs(path: str | os.PathLike, pairs: dict[str, np.ndarray]) -> None:
    """Write a pairs file: source [M,N,3], target [M,N',3], rotation [M,3,3], translation [M,3]."""
    np.savez_compressed(path, **{k: v for k, v in pairs.items() if v is not None})


def load_pairs(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read and check a pairs file (``target ~= rotation @ source + translation``)."""
    with np.load(path, allow_pickle=False) as d:
        missing = [k for k in PAIR_KEYS if k not in d.files]
        if missing:
            raise ValueError(f"pairs file {path} lacks {missing}")
        pairs = {k: d[k] for k in d.files}
    M = len(pairs["source"])
    src, tgt = pairs["source"], pairs["target"]
    if src.ndim != 3 or src.shape[-1] != 3 or tgt.ndim != 3 or tgt.shape[-1] != 3 or len(tgt) != M:
        raise ValueError(f"source/target must be [M, N, 3]; got {src.shape} and {tgt.shape}")
    if pairs["rotation"].shape != (M, 3, 3) or pairs["translation"].shape != (M, 3):
        raise ValueError("rotation must be [M, 3, 3] and translation [M, 3]")
    for k in PAIR_KEYS:
        pairs[k] = pairs[k].astype(np.float32)
    return pairs


class TrainPairStream:
    """Endless random training pairs from a shape array, one fresh pair per shape per epoch."""

    def __init__(self, shapes: np.ndarray, protocol: PairProtocol, seed: int):
        self.shapes, self.protocol, self.seed = shapes, protocol, seed

    def epoch(self, epoch: int, batch_size: int):
        """Yield batches (dicts of float32 arrays) of one epoch; reproducible per (seed, epoch)."""
        rng = np.random.default_rng([self.seed, epoch])
        order = rng.permutation(len(self.shapes))
        for start in range(0, len(order) - batch_size + 1, batch_size):
            yield make_pairs(self.shapes[order[start : start + batch_size]], self.protocol, rng)
