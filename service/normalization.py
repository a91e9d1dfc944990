"""One similarity normalisation for a source/target pair, and the way back to the caller's units.

Each cloud is centred at its own centroid and both are divided by one COMMON scale, so that a rigid
pose between the normalised clouds is a rigid pose between the originals (a different scale per
cloud would not be).  The scale makes the source's RMS radius equal ``reference_radius`` (the
radius of the clouds the network was trained on).

With ``src_n = (src - c_s) / s`` and ``tgt_n = (tgt - c_t) / s``, a pose ``tgt_n ≈ R src_n + t``
is, in the caller's units, ``tgt ≈ R src + t'`` with ``t' = s t + c_t - R c_s``
(:meth:`Normalization.unnormalize_pose`; :meth:`Normalization.normalize_pose` is its inverse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _check_cloud(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ValueError(f"{name} must be (N, 3) with N >= 1, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} contains NaN or Inf")
    return points


def rms_radius(points: np.ndarray) -> float:
    """RMS distance of ``points (N, 3)`` from their centroid (the scale statistic of ``fit``)."""
    points = np.asarray(points, dtype=np.float64)
    return _rms_radius(points, points.mean(axis=0))


def _rms_radius(points_in_frame: np.ndarray, center: np.ndarray) -> float:
    """RMS distance of ``points (N, 3)`` from ``center (3,)``."""
    return float(np.sqrt(np.mean(np.sum((points_in_frame - center) ** 2, axis=1))))


@dataclass(frozen=True)
class Normalization:
    """Centres ``src_center (3,)``, ``tgt_center (3,)`` (float64) and the common ``scale`` (> 0)."""

    src_center: np.ndarray  # [3]
    tgt_center: np.ndarray  # [3]
    scale: float

    @classmethod
    def fit(cls, src: np.ndarray, tgt: np.ndarray, reference_radius: float) -> Normalization:
        """Normalisation of the pair ``src (N, 3)``, ``tgt (M, 3)``.

        ``scale`` is the RMS distance of the source points from their centroid divided by
        ``reference_radius``; if that is zero or not finite the target's is used, and if both are
        degenerate (single points, identical points) the scale is 1.

        Raises:
            ValueError: a cloud is not ``(N >= 1, 3)`` or not finite, or ``reference_radius`` is not
                positive.
        """
        src = _check_cloud(src, "src").astype(np.float64)
        tgt = _check_cloud(tgt, "tgt").astype(np.float64)
        if not (np.isfinite(reference_radius) and reference_radius > 0):
            raise ValueError(f"reference_radius must be positive and finite, got {reference_radius}")
        src_center = src.mean(axis=0)  # [3]
        tgt_center = tgt.mean(axis=0)  # [3]
        scale = 1.0
        for points, center in ((src, src_center), (tgt, tgt_center)):
            candidate = _rms_radius(points, center) / reference_radius
            if np.isfinite(candidate) and candidate > 0:
                scale = candidate
                break
        return cls(src_center=src_center, tgt_center=tgt_center, scale=float(scale))

    def apply_src(self, points_in_src: np.ndarray) -> np.ndarray:
        """``(points - src_center) / scale`` for ``(N, 3)`` points, in their float dtype (float32 min)."""
        return self._apply(points_in_src, self.src_center)

    def apply_tgt(self, points_in_tgt: np.ndarray) -> np.ndarray:
        """``(points - tgt_center) / scale`` for ``(N, 3)`` points, in their float dtype (float32 min)."""
        return self._apply(points_in_tgt, self.tgt_center)

    def _apply(self, points: np.ndarray, center: np.ndarray) -> np.ndarray:
        points = np.asarray(points)
        dtype = np.result_type(points.dtype, np.float32)
        return ((points.astype(np.float64) - center) / self.scale).astype(dtype)

    def unnormalize_pose(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose between normalised clouds -> ``src_to_tgt`` pose in the caller's units.

        Args:
            R: ``(..., 3, 3)`` rotation with ``tgt_n ≈ R src_n + t``.
            t: ``(..., 3)`` translation in normalised units.

        Returns:
            ``R`` unchanged (float64) and ``t' = scale * t + tgt_center - R src_center`` ``(..., 3)``.
        """
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        return R, self.scale * t + self.tgt_center - np.einsum("...ij,j->...i", R, self.src_center)

    def normalize_pose(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of :meth:`unnormalize_pose`: caller's ``src_to_tgt`` pose -> normalised units."""
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        return R, (t - self.tgt_center + np.einsum("...ij,j->...i", R, self.src_center)) / self.scale
