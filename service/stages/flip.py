"""Stage 5c, flip check (after the rotation search): the half turns of a result that still fits poorly.

An elongated or near-symmetric object seen in part (a range image of the dragon) can come back from the search turned
half a turn about one of its axes: the flipped shape overlaps the target along its length, and none of the search's
candidates lay in the right basin. With a target that samples the caller's surface densely
(:func:`service.stages.ranking.samples_the_surface`), a searched pose that fits poorly
(:func:`service.stages.slide.fits_poorly`) competes with its three half turns about the moved working source's
principal axes (:func:`service.stages.partial.half_turns`). A half turn through the source's centroid turns the
shape right but need not place it right (a room fragment's right place lies metres away), so each half turn's
rotation is also tried at its best candidate translations (:func:`service.stages.ranking.with_translations`, as the
search's candidates are), and all are briefly refined like the search's candidates; one whose
:func:`service.stages.ranking.close_fit` exceeds the pose's by ``FLIP_MARGIN`` gets the full refinement and takes its
place, with this ranking's ambiguity instead of the search's, which was about the pose it replaces
(``docs/decisions/0016-flip-check-after-the-search.md``, ``0017-half-turns-at-their-best-translations.md``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from service.options import RegistrationOptions
from service.stages.normalise import Working
from service.stages.partial import half_turns
from service.stages.ranking import FIT_NAME, close_fit, ranking_ambiguity, samples_the_surface, with_translations
from service.stages.refine import Refined, icp_distance, refine_pose, short_refine
from service.stages.slide import fits_poorly

FLIP_MARGIN = 0.03  # close fit a half turn must gain over the pose (service.rotation_search.AMBIGUOUS_RATIO_GAP)


def flip(work: Working, refined: Refined, options: RegistrationOptions) -> Refined:
    """``refined`` unless the target is dense, it fits poorly and one of its half turns (at the turn's own place or at
    one of its rotation's best translations), briefly refined, fits more closely by ``FLIP_MARGIN``: then that one
    after the full refinement, ambiguous where another of them fits almost as well elsewhere."""
    mode = options.refine_mode
    if (mode == "none" or not samples_the_surface(work)
            or not fits_poorly(work, refined.rotation, refined.translation)):
        return refined
    distance = icp_distance(work, options)
    R_h, t_h = half_turns(work.working_source, refined.rotation, refined.translation)  # [3, 3, 3], [3, 3]
    starts, _ = with_translations(work, list(zip(R_h, t_h, strict=True)))  # the turns, then each at other places
    R_s, t_s = short_refine(work, starts, mode, distance, refined.surface)  # [C, 3, 3], [C, 3]
    rotations = np.concatenate([refined.rotation[None], R_s])  # [1 + C, 3, 3]: the pose, then the starts
    translations = np.concatenate([refined.translation[None], t_s])  # [1 + C, 3]
    fits = close_fit(work, rotations, translations)  # [1 + C]
    best = int(np.argmax(fits[1:])) + 1
    if fits[best] <= fits[0] + FLIP_MARGIN:
        return refined
    full = refine_pose(work, R_s[best - 1], t_s[best - 1], mode, distance, options.icp_max_iterations,
                       refined.surface)
    ambiguity = ranking_ambiguity(work, rotations, translations, fits, best, measure=FIT_NAME)  # not the search's
    return dataclasses.replace(refined, rotation=full.rotation, translation=full.translation, warnings=full.warnings,
                               ambiguity=ambiguity)
