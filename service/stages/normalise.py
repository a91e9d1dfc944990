"""Stage 3, normalise: the similarity normalisation of the working clouds, and poses back to the caller's units."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.normalization import Normalization
from service.procrustes import compose
from service.stages.sample import Sampled

INLIER_DISTANCE = 0.05  # normalised units (the paper's match threshold): quality inliers
ICP_DISTANCE = 0.1  # normalised units: default ICP correspondence distance


@dataclass(frozen=True, eq=False)
class Working:
    """One registration's working clouds, shared by the plain pass and the search of ``rotation_search="auto"``."""

    src: np.ndarray  # [N, 3] the caller's source (float64)
    idx_s: np.ndarray  # [Ns] working source rows
    idx_t: np.ndarray  # [Nt] working target rows
    src_w: np.ndarray  # [Ns, 3] working source, moved by the initial guess
    tgt_w: np.ndarray  # [Nt, 3] working target, caller's units
    src_r: np.ndarray  # [Nr, 3] the source points the refinement moves, caller's units
    tgt_r: np.ndarray  # [Mr, 3] the target points it aligns them with
    norm: Normalization
    src_n: np.ndarray  # [Ns, 3] float32, normalised (after the initial guess)
    tgt_n: np.ndarray  # [Nt, 3] float32, normalised
    R_init: np.ndarray  # [3, 3] initial guess
    t_init: np.ndarray  # [3]
    src_e: np.ndarray  # [Ne, 3] the caller's source after the entry reduction (caller's units)
    tgt_e: np.ndarray  # [Me, 3] the target after the entry reduction

    @property
    def inlier_distance(self) -> float:
        """``INLIER_DISTANCE`` in the caller's units."""
        return INLIER_DISTANCE * self.norm.scale


def normalise(sampled: Sampled, reference_radius: float) -> Working:
    """Fit :class:`service.normalization.Normalization` to the working clouds and apply it (float32)."""
    s = sampled
    norm = Normalization.fit(s.src_w, s.tgt_w, reference_radius)
    src_n, tgt_n = norm.apply_src(s.src_w).astype(np.float32), norm.apply_tgt(s.tgt_w).astype(np.float32)
    return Working(s.src, s.idx_s, s.idx_t, s.src_w, s.tgt_w, s.src_r, s.tgt_r, norm, src_n, tgt_n, s.R_init,
                   s.t_init, s.src_e, s.tgt_e)


def to_caller(work: Working, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose between normalised clouds -> caller's ``src_to_tgt``, composed after the initial guess."""
    R_c, t_c = work.norm.unnormalize_pose(R, t)
    return compose(R_c, t_c, work.R_init, work.t_init)
