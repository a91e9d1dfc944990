"""What ``Registrar.register`` returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.procrustes import to_matrix


@dataclass
class IterationPose:
    rotation: np.ndarray  # [3, 3] cumulative src_to_tgt after this iteration (caller's units)
    translation: np.ndarray  # [3]


@dataclass
class RegistrationResult:
    rotation: np.ndarray  # [3, 3] src_to_tgt
    translation: np.ndarray  # [3]
    source_index: np.ndarray  # [K] int64 into the caller's source array
    target_index: np.ndarray  # [K] int64 into the caller's target array
    credibility: np.ndarray  # [K] sigmoid of the credibility logit, in [0, 1]
    weight: np.ndarray  # [K] SVD weight after the median threshold (sums to ~1)
    inlier_ratio: float
    residual_rms: float
    reliable: bool
    warnings: list[str]
    iterations: int
    timing_ms: dict[str, float]
    iteration_poses: list[IterationPose] = field(default_factory=list)
    stability: float | None = None  # service.stability: weakly constrained below WEAK_EIGENVALUE (dense targets: 0.02)

    @property
    def transform(self) -> np.ndarray:
        """``[4, 4]`` homogeneous src_to_tgt."""
        return to_matrix(self.rotation, self.translation)
