"""Network configuration (one dataclass, saved beside every checkpoint and in every manifest)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class MFGNetConfig:
    """Hyper-parameters of the MFGNet network.

    ``feature_diff`` and ``centroid`` select between the paper (the project's own models) and the
    authors' released checkpoints, which use ``target_minus_source`` and ``unweighted``.
    """

    iterations: int = 4  # n: matching + SVD iterations
    keypoints: int = 128  # K at test time (top-K by significance)
    knn: int = 12  # k of the edge-convolution graph (the point itself included)
    emb_dims: int = 64  # embedding size of the encoder
    encoder_blocks: int = 5  # edge-convolution blocks in sequence
    matcher_channels: int = 32  # hidden width of the F / S matchers and the credibility head
    share_weights: bool = False  # one matcher set for every iteration (else one per iteration)
    feature_diff: Literal["source_minus_target", "target_minus_source"] = "source_minus_target"
    centroid: Literal["weighted", "unweighted"] = "weighted"
    clamp: float = 20.0  # matching matrix clamp(F + S, -clamp, clamp)
    match_threshold: float = 0.05  # th: ground-truth correspondence distance for the losses
    train_positives: int = 64  # sampled keypoints with a partner (training only)
    train_negatives: int = 64  # sampled keypoints without a partner (training only)

    @property
    def weight_sets(self) -> int:
        """Number of distinct matcher / credibility weight sets."""
        return 1 if self.share_weights else self.iterations

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> MFGNetConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


OFFICIAL_CONFIG = MFGNetConfig(
    iterations=3, keypoints=256, feature_diff="target_minus_source", centroid="unweighted"
)
