"""Stage 2, sample: the working clouds the network sees and the clouds the refinement moves.

Clouds above :data:`service.reduction.ENTRY_LIMIT` points are first reduced to about that many
(:func:`service.reduction.entry_indices`), so that every later stage costs the same on a 2,000,000-point scan as on
a 100,000-point one; every returned row still indexes the caller's arrays. The rows kept are moved to each cloud's
origin (:mod:`service.stages.anchor`): the caller's arrays are read, not copied whole nor written.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.reduction import entry_indices
from service.sampling import resample_indices, spread_indices
from service.stages.validate import Request


@dataclass(frozen=True, eq=False)
class Sampled:
    working_source: np.ndarray  # [Ns, 3] float64, the working source's rows of the source (``src_w`` before the guess)
    idx_s: np.ndarray  # [Ns] working source rows
    idx_t: np.ndarray  # [Nt] working target rows
    src_w: np.ndarray  # [Ns, 3] working source, moved by the initial guess
    tgt_w: np.ndarray  # [Nt, 3] working target, caller's units
    src_r: np.ndarray  # [Nr, 3] the source points the refinement moves, caller's units
    tgt_r: np.ndarray  # [Mr, 3] the target points it aligns them with
    R_init: np.ndarray  # [3, 3] initial guess
    t_init: np.ndarray  # [3]
    src_e: np.ndarray  # [Ne, 3] the source after the entry reduction (all of it up to ENTRY_LIMIT), about its origin
    tgt_e: np.ndarray  # [Me, 3] the target after the entry reduction, the same

    @property
    def refines_on_working_clouds(self) -> bool:
        """Whether the refinements move the working source onto the working target: ``refine_points`` unset, at or
        below the working size, or giving a sample thinner than a working cloud (decision 0119)."""
        return self.src_r is self.working_source and self.tgt_r is self.tgt_w


def sample(request: Request) -> Sampled:
    """``working_size`` rows of each cloud (:func:`service.sampling.resample_indices`; isolated points left out
    with ``drop_isolated``); the refinement's clouds are the working ones unless ``refine_points`` asks for more."""
    o = request.options
    src_e, to_s = entered(request.src, request.src_anchor)  # [Ne, 3] and its row map to the caller's rows
    tgt_e, to_t = entered(request.tgt, request.tgt_anchor)  # [Me, 3]
    src_moved = src_e @ request.R_init.T + request.t_init  # [Ne, 3] source in the initial guess's frame
    local_s = resample_indices(src_moved, o.working_size, o.drop_isolated)  # [Ns] rows of src_e
    local_t = resample_indices(tgt_e, o.working_size, o.drop_isolated)  # [Nt] rows of tgt_e
    working_source, src_w, tgt_w = src_e[local_s], src_moved[local_s], tgt_e[local_t]
    src_r, tgt_r = working_source, tgt_w
    if o.extra_refine_points is not None:  # RegistrationOptions refuses refine_points without a refinement
        spread_s = spread_indices(src_moved, o.extra_refine_points, o.drop_isolated)  # [Nr] rows of src_e
        spread_t = spread_indices(tgt_e, o.extra_refine_points, o.drop_isolated)  # [Mr] rows of tgt_e
        # a spread sample may hold fewer points than asked (one per voxel, less sparse voxels and isolated points):
        # where either is thinner than its working cloud, the request refines as without refine_points (decision 0119)
        if len(spread_s) >= len(local_s) and len(spread_t) >= len(local_t):
            src_r, tgt_r = src_e[spread_s], tgt_e[spread_t]  # [Nr, 3], [Mr, 3]
    return Sampled(working_source, to_s(local_s), to_t(local_t), src_w, tgt_w, src_r, tgt_r, request.R_init,
                   request.t_init, src_e, tgt_e)


def entered(points: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """``points [N, 3]`` after the entry reduction, minus ``origin [3]`` (a new array of at most about
    ``ENTRY_LIMIT`` rows), and the map from its rows to the caller's."""
    kept = entry_indices(points, origin=origin)
    if kept is None:
        return points - origin, lambda rows: rows
    return points[kept] - origin, lambda rows: kept[rows]
