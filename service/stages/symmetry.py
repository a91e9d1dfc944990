"""Stage 8, symmetry check: a ``reliable`` result whose half turns fit almost as well is ambiguous.

A near-symmetric shape (a bathtub, a bench) seen from two views overlays the target about as well
turned half a turn about one of its axes: the inlier ratio and the close fit cannot tell the two poses apart, and a
search that never reached the other basin has no close second to flag (:func:`service.rotation_search.ambiguity_warning`
needs one). So the final pose of a result about to be called ``reliable`` competes with its three half turns about the
moved working source's principal axes (:func:`service.stages.partial.half_turns`), each briefly refined as the search's
candidates are (:func:`service.stages.refine.short_refine`), ranked by the fit the search ranks by
(:func:`service.stages.ranking.candidate_fits`); one within ``AMBIGUOUS_RATIO_GAP`` of the pose's fit, or above it,
makes the result ambiguous: not ``reliable``, with a warning. The pose itself is kept
(``docs/decisions/0030-half-turn-symmetry-check.md``).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from service.options import RegistrationOptions
from service.result import RegistrationResult
from service.rotation_search import ambiguity_warning
from service.stages.normalise import Working
from service.stages.partial import half_turns
from service.stages.ranking import candidate_fits
from service.stages.refine import icp_distance, short_refine


def symmetry(work: Working, result: RegistrationResult, options: RegistrationOptions,
             timing: dict[str, float]) -> RegistrationResult:
    """``result``, not ``reliable`` and with :func:`half_turn_ambiguity`'s warning where it gives one; only results
    that are ``reliable`` and refined are checked. The time is added to ``timing["postprocess"]``."""
    if not result.reliable or options.refine_mode == "none":
        return result
    started = time.perf_counter()
    warning = half_turn_ambiguity(work, result.rotation, result.translation, options)
    timing["postprocess"] = timing.get("postprocess", 0.0) + 1000 * (time.perf_counter() - started)
    if warning is None:
        return result
    return dataclasses.replace(result, reliable=False, warnings=[*result.warnings, warning])


def half_turn_ambiguity(work: Working, R: np.ndarray, t: np.ndarray, options: RegistrationOptions) -> str | None:
    """The ambiguity warning of the pose ``R [3, 3], t [3]`` (caller's units) against its three half turns after the
    search's short refinement, or ``None`` where each of them fits worse by more than ``AMBIGUOUS_RATIO_GAP``."""
    mode = options.refine_mode
    surface = work.target_surface if mode != "icp" else None
    R_h, t_h = half_turns(work.working_source, R, t)  # [3, 3, 3], [3, 3]
    R_s, t_s = short_refine(work, list(zip(R_h, t_h, strict=True)), mode, icp_distance(work, options), surface)
    rotations = np.concatenate([R[None], R_s])  # [4, 3, 3]: the pose, then its turns
    translations = np.concatenate([t[None], t_s])  # [4, 3]
    fits, measure = candidate_fits(work, rotations, translations)  # [4]
    return ambiguity_warning(rotations, fits, 0, measure=measure)
