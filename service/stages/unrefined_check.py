"""Unrefined check: with ``refine: "none"``, a ``reliable`` pose is one a short refinement leaves where it is.

The network's pose is returned as it is, for the lowest latency. Its fit alone cannot tell a pose a few degrees off
from a right one (a smooth surface still lays most of the source near the target 5-10 deg off), nor, on
near-symmetric shapes, one tens of degrees off: the README's surface came back 19-53 deg off, `reliable`. So a result
about to be called ``reliable`` is refined briefly from its pose (point-to-plane, ``CHECK_ITERATIONS`` updates of the
search candidates' short points, or of every working point where those are fewer than ``CHECK_POINTS``), and where
that turns it more than ``MOVE_DEG`` or moves the working source's centroid more than ``SHIFT`` inlier distances (the
working target's median spacing where that is wider), the pose is not at a fit's optimum: not ``reliable``, with a
``poor fit`` warning. The returned pose stays the network's
(``docs/decisions/0116-an-unrefined-pose-a-short-refinement-leaves.md``).
"""

from __future__ import annotations

import time

import numpy as np

from service.icp_batch import refine_plane_many
from service.options import RegistrationOptions
from service.quality import POOR_FIT
from service.result import RegistrationResult
from service.rotation_search import rotation_between_deg
from service.stages.normalise import ICP_DISTANCE, Working
from service.stages.withdraw import withdrawn

CHECK_ITERATIONS = 10  # updates of the short refinement
# Points it moves at least: the search candidates' short points (every third working point) where they reach this
# many (the default working size, 768, gives 256), else every working point: 43 points of a 128-point working cloud
# turned right poses up to 27 deg
CHECK_POINTS = 256
MOVE_DEG = 5.0  # a right pose is within this of the truth: a refinement that turns it further found another fit
SHIFT = 1.0  # the working source's centroid may move this many inlier distances (or target spacings, if wider)


def unrefined_check(
    work: Working, result: RegistrationResult, options: RegistrationOptions, timing: dict[str, float]
) -> RegistrationResult:
    """``result``, not ``reliable`` and with a ``poor fit`` warning where a short point-to-plane refinement from its
    unrefined pose turns it more than ``MOVE_DEG`` or moves it more than ``SHIFT`` inlier distances; only ``reliable``
    results of ``refine: "none"`` are checked. The time is added to ``timing["postprocess"]``."""
    if options.refine_mode != "none" or not result.reliable:
        return result
    started = time.perf_counter()
    R, t = result.rotation, result.translation  # [3, 3], [3] caller's units
    short = len(work.short_points) >= CHECK_POINTS
    moved, surface = (work.short_points, work.short_surface) if short else (
        np.asarray(work.src_r, dtype=np.float64), work.source_surface)  # [Nc, 3]
    # at the default correspondence distance: refine "none" refuses icp_max_distance (it sets a refinement)
    R_s, t_s = refine_plane_many(moved, work.tgt_r, R[None], t[None], max_distance=ICP_DISTANCE * work.norm.scale,
                                 max_iterations=CHECK_ITERATIONS, target=work.target_surface,
                                 source=surface)  # [1, 3, 3], [1, 3]
    turned = rotation_between_deg(R, R_s[0])
    centre = work.working_source.mean(axis=0)  # [3]
    unit = max(work.inlier_distance, float(np.median(work.target_spacings)))  # sparse working clouds: their spacing
    moved_by = float(np.linalg.norm((R_s[0] @ centre + t_s[0]) - (R @ centre + t)))  # caller's units
    shifted = moved_by / unit
    timing["postprocess"] = timing.get("postprocess", 0.0) + 1000 * (time.perf_counter() - started)
    if turned <= MOVE_DEG and shifted <= SHIFT:
        return result
    # the message counts inlier distances, as it says, and names the allowed shift in them (wider on sparse clouds)
    return withdrawn(result, f"{POOR_FIT}: a short refinement turns the unrefined pose {turned:.1f} deg and moves it "
                             f"{moved_by / work.inlier_distance:.1f} inlier distances (more than {MOVE_DEG:g} deg or "
                             f"{SHIFT * unit / work.inlier_distance:.3g}); a "
                             "refinement (refine: icp-plane) settles it or shows it wrong")
