"""Stage 5b, slide check: other translations for the refined rotation when the refined pose fits poorly.

On room-sized fragments the rotation is often right while the translation is metres off: with the rotation
fixed, the clouds slid along walls and floors into a wrong local fit. When the refined pose's inlier ratio is
below ``SLIDE_TRIGGER`` of what the target's density allows, the occupancy cross-correlation of
:mod:`service.translation_search` proposes the translations that overlay the turned source on the target best;
each gets the search candidates' short refinement, they are ranked with the current pose
(:func:`service.stages.ranking.rank_candidates`: by their close fit to a dense target; the current pose wins
ties), and a new winner gets the full refinement -- with a dense target kept unless it fits less closely than its
start: on the working clouds of a room the refinement can slide a right place along the walls again
(``docs/decisions/0014-places-by-their-close-fit.md``). Another place that fits almost as well makes the result
ambiguous (:func:`service.stages.ranking.shift_ambiguity`), whichever wins.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import numpy as np

from service.icp import IcpResult
from service.options import RegistrationOptions
from service.rotation_search import rank_hypotheses
from service.stages.normalise import Working
from service.stages.ranking import close_fit, rank_candidates, samples_the_surface
from service.stages.refine import Refined, icp_distance, refine_pose, short_refine
from service.translation_search import translation_candidates

SLIDE_TRIGGER = 0.8  # share of the attainable inlier ratio below which the slide check runs


def overlaid_share(work: Working, R: np.ndarray, t: np.ndarray) -> float:
    """The share of working source points the caller's pose ``R, t`` brings within an inlier distance of the working
    target (the inlier ratio :func:`service.rotation_search.rank_hypotheses` ranks by)."""
    return float(rank_hypotheses(work.working_source, work.tgt_w, R[None], t[None], work.inlier_distance)[1][0])


def fits_poorly(work: Working, R: np.ndarray, t: np.ndarray, trigger: float = SLIDE_TRIGGER) -> bool:
    """Whether the caller's pose ``R, t`` overlays fewer working source points on the target (:func:`overlaid_share`)
    than ``trigger`` times the share a right pose reaches at the target's density
    (:func:`service.quality.attainable_inlier_ratio`)."""
    return overlaid_share(work, R, t) < trigger * work.attainable_ratio


def slide(work: Working, refined: Refined, options: RegistrationOptions, trigger: float = SLIDE_TRIGGER) -> Refined:
    """``refined`` unless it fits poorly (:func:`fits_poorly` at ``trigger``) and one of the candidate translations
    for its rotation fits better."""
    mode = options.refine_mode
    if mode == "none" or not fits_poorly(work, refined.rotation, refined.translation, trigger):
        return refined
    R, t, distance = refined.rotation, refined.translation, icp_distance(work, options)
    short = partial(short_refine, work, refine=mode, distance=distance, surface=refined.surface)
    moved = work.src_e @ R.T  # [Ne, 3] the caller's source turned by R
    starts = [(R, t)] + [(R, shift) for shift in translation_candidates(moved, work.tgt_e)]
    ranked = rank_candidates(work, starts, short)
    ambiguity = refined.ambiguity or ranked.ambiguity  # another place fitting almost as well is a doubt either way
    if ranked.pick == 0:
        return refined if ambiguity == refined.ambiguity else dataclasses.replace(refined, ambiguity=ambiguity)
    full = refine_pose(work, ranked.rotation, ranked.translation, mode, distance, options.icp_max_iterations,
                       refined.surface)
    rotation, translation, warnings = closer_of(work, full, ranked.rotation, ranked.translation)
    return dataclasses.replace(refined, rotation=rotation, translation=translation, warnings=warnings,
                               ambiguity=ambiguity)


def closer_of(work: Working, full: IcpResult, R: np.ndarray, t: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """The full refinement's pose and warnings, or its start ``R, t`` (no warnings) where the entered target
    :func:`service.stages.ranking.samples_the_surface` and the start has the higher
    :func:`service.stages.ranking.close_fit` (ties: the refinement)."""
    if not samples_the_surface(work):
        return full.rotation, full.translation, full.warnings
    fits = close_fit(work, np.stack([full.rotation, R]), np.stack([full.translation, t]))  # [2]
    if fits[1] > fits[0]:
        return R, t, ()
    return full.rotation, full.translation, full.warnings
