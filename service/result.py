"""What ``Registrar.register`` returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.pose_json import rotation_fields
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

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """``[4]`` the rotation as a unit quaternion, scalar last (ROS ``geometry_msgs/Quaternion``), ``w >= 0``: the
        response's ``quaternion_xyzw``."""
        return rotation_fields(self.rotation)["quaternion_xyzw"]

    @property
    def euler_zyx_deg(self) -> np.ndarray:
        """``[3]`` ``[a, b, c]`` degrees, extrinsic: ``R = Rx(c) Ry(b) Rz(a)`` (the response's ``euler_zyx_deg``)."""
        return rotation_fields(self.rotation)["euler_zyx_deg"]

    @property
    def yaw_pitch_roll_deg(self) -> np.ndarray:
        """``[3]`` degrees, intrinsic: ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (the response's ``yaw_pitch_roll_deg``)."""
        return rotation_fields(self.rotation)["yaw_pitch_roll_deg"]
