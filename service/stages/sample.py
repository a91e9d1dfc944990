"""Stage 2, sample: the working clouds the network sees and the clouds the refinement moves."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.sampling import resample_indices, spread_indices
from service.stages.validate import Request


@dataclass(frozen=True, eq=False)
class Sampled:
    src: np.ndarray  # [N, 3] the caller's source (float64)
    idx_s: np.ndarray  # [Ns] working source rows
    idx_t: np.ndarray  # [Nt] working target rows
    src_w: np.ndarray  # [Ns, 3] working source, moved by the initial guess
    tgt_w: np.ndarray  # [Nt, 3] working target, caller's units
    src_r: np.ndarray  # [Nr, 3] the source points the refinement moves, caller's units
    tgt_r: np.ndarray  # [Mr, 3] the target points it aligns them with
    R_init: np.ndarray  # [3, 3] initial guess
    t_init: np.ndarray  # [3]


def sample(request: Request) -> Sampled:
    """``working_size`` rows of each cloud (:func:`service.sampling.resample_indices`; isolated points left out
    with ``drop_isolated``); the refinement's clouds are the working ones unless ``refine_points`` asks for more."""
    o = request.options
    src, tgt = request.src, request.tgt
    src_moved = src @ request.R_init.T + request.t_init  # [N, 3] source in the initial guess's frame
    idx_s = resample_indices(src_moved, o.working_size, o.drop_isolated)  # [Ns] into the caller's source
    idx_t = resample_indices(tgt, o.working_size, o.drop_isolated)  # [Nt]
    src_w, tgt_w = src_moved[idx_s], tgt[idx_t]
    src_r, tgt_r = src[idx_s], tgt_w
    if o.refine_points is not None and o.refine_mode != "none":
        src_r = src[spread_indices(src_moved, int(o.refine_points), o.drop_isolated)]  # [Nr, 3]
        tgt_r = tgt[spread_indices(tgt, int(o.refine_points), o.drop_isolated)]  # [Mr, 3]
    return Sampled(src, idx_s, idx_t, src_w, tgt_w, src_r, tgt_r, request.R_init, request.t_init)
