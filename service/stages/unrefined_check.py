"""Unrefined check: with ``refine: "none"``, a ``reliable`` pose is one a short refinement leaves where it is.

The network's pose is returned as it is, for the lowest latency. Its fit alone cannot tell a pose a few degrees off
from a right one (a smooth surface still lays most of the source near the target 5-10 deg off), nor, on
near-symmetric shapes, one tens of degrees off: the README's surface came back 19-53 deg off, `reliable`. So a result
about to be called ``reliable`` is refined briefly from its pose (point-to-plane, ``CHECK_ITERATIONS`` updates of the
short working points, as the search's candidates are: :func:`service.stages.refine.short_refine`), and where that moves
it more than ``MOVE_DEG`` or moves the working source's centroid more than ``SHIFT`` inlier distances, the pose is not
at a fit's optimum: not ``reliable``, with a ``poor fit`` warning. The returned pose stays the network's
(``docs/decisions/0116-an-unrefined-pose-a-short-refinement-leaves.md``).
"""

from __future__ import annotations

import time

import numpy as np

from service.options import RegistrationOptions
from service.quality import POOR_FIT
from service.result import RegistrationResult
from service.rotation_search import rotation_between_deg
from service.stages.normalise import Working
from service.stages.refine import icp_distance, short_refine
from service.stages.withdraw import withdrawn

CHECK_ITERATIONS = 10  # updates of the short refinement
MOVE_DEG = 5.0  # a right pose is within this of the truth: a refinement that turns it further found another fit
SHIFT = 1.0  # inlier distances the working source's centroid may move


def unrefined_check(
    work: Working, result: RegistrationResult, options: RegistrationOptions, timing: dict[str, float]
) -> RegistrationResult:
    """``result``, not ``reliable`` and with a ``poor fit`` warning where a short point-to-plane refinement from its
    unrefined pose moves it more than ``MOVE_DEG`` or ``SHIFT`` inlier distances; only ``reliable`` results of
    ``refine: "none"`` are checked. The time is added to ``timing["postprocess"]``."""
    if options.refine_mode != "none" or not result.reliable:
        return result
    started = time.perf_counter()
    R, t = result.rotation, result.translation  # [3, 3], [3] caller's units
    R_s, t_s = short_refine(work, [(R, t)], "icp-plane", icp_distance(work, options), work.target_surface,
                            CHECK_ITERATIONS)  # [1, 3, 3], [1, 3]
    turned = rotation_between_deg(R, R_s[0])
    centre = work.working_source.mean(axis=0)  # [3]
    shifted = float(np.linalg.norm((R_s[0] @ centre + t_s[0]) - (R @ centre + t))) / work.inlier_distance
    timing["postprocess"] = timing.get("postprocess", 0.0) + 1000 * (time.perf_counter() - started)
    if turned <= MOVE_DEG and shifted <= SHIFT:
        return result
    return withdrawn(result, f"{POOR_FIT}: a short refinement moves the unrefined pose {turned:.1f} deg and "
                             f"{shifted:.1f} inlier distances (more than {MOVE_DEG:g} deg or {SHIFT:g}); a "
                             "refinement (refine: icp-plane) settles it or shows it wrong")
