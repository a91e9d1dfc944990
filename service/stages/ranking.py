"""Candidate ranking (within the refine stage): the rotation search's kept candidates each get a short
refinement and are ranked again: by their :func:`close_fit` to the caller's target where it is dense, then by their
fit on the working clouds; the slide check ranks its places the same way.

The search's own ranking (short point-to-point ICPs on its subsample) often put a wrong basin first: on 600
seeded pairs at 90 and 180 degrees 359 -> 388 right for ~15 ms more
(``docs/decisions/0002-rotation-search-default-and-trigger.md``, "Inside the search"). A close second that is turned
far from the winner, or that places the source far from it, makes the ranking ambiguous
(``docs/decisions/0008-ambiguous-places.md``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.rotation_search import (
    AMBIGUOUS_RATIO_GAP,
    ambiguity_warning,
    close_second,
    fits_as,
    rank_hypotheses,
)
from service.stages.normalise import Working, samples_densely
from service.translation_search import translation_candidates

CANDIDATE_SHIFTS = 2  # translations tried with each rotation search candidate's rotation
# Another ranked candidate that places the source's centroid more than AMBIGUOUS_SHIFT (normalised units) from the
# winner's place, with a fit (as ranked) within service.rotation_search.AMBIGUOUS_RATIO_GAP of the winner's, makes the
# result ambiguous (not reliable, a warning): room fragments slide along walls and floors into places that fit
# almost as well.
AMBIGUOUS_SHIFT = 0.2
# close_fit counts a working source point as on the target within CLOSE_FIT of the inlier distance of the entered
# target's points (docs/decisions/0014-places-by-their-close-fit.md).
CLOSE_FIT = 0.5
FIT_NAME = "close fit"  # what the ambiguity warnings of a ranking call the close fit
SHIFT_AMBIGUITY = "ambiguous: a pose that moves the source"  # first words of the warning of another place that fits


def with_translations(work: Working, starts: list[tuple[np.ndarray, np.ndarray]], count: int = CANDIDATE_SHIFTS
                      ) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[int]]:
    """``starts`` (caller's poses), then each start's rotation at its ``count`` best candidate translations
    (:func:`service.translation_search.translation_candidates`), and for every returned pose the index of the start
    it came from. The rotation search's candidates often hold the right rotation at a wrong translation."""
    poses, origin = list(starts), list(range(len(starts)))
    for index, (R, t) in enumerate(starts):
        shifts = translation_candidates(work.src_e @ R.T, work.tgt_e, count)  # [C, 3]
        shifts = shifts[np.linalg.norm(shifts - t, axis=1) > work.inlier_distance]  # not the start's own place
        poses += [(R, shift) for shift in shifts]
        origin += [index] * len(shifts)
    return poses, origin


@dataclass(frozen=True, eq=False)
class Ranked:
    pick: int  # index of the winning start
    ambiguity: str | None  # service.rotation_search.ambiguity_warning of the ranking
    rotation: np.ndarray  # [3, 3] the winner's briefly refined src_to_tgt (caller's units)
    translation: np.ndarray  # [3]
    rotations: np.ndarray  # [C, 3, 3] every candidate, briefly refined
    translations: np.ndarray  # [C, 3]
    fits: np.ndarray  # [C] the fit they were ranked by


def close_fit(work: Working, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """``[C]``: the share of the working source points that each pose (``rotations [C, 3, 3]``, ``translations
    [C, 3]``, caller's units) places within ``CLOSE_FIT`` inlier distances of the entered target ``tgt_e``.

    Distances to the target's surface, not to its working samples: on room-sized clouds those lie farther apart
    than an inlier distance, and places slid along a wall overlay about as many source points on them as the
    right place does."""
    reach = CLOSE_FIT * work.inlier_distance
    moved = work.working_source @ rotations.transpose(0, 2, 1) + translations[:, None]  # [C, Ns, 3]
    dist, _ = work.entered_target_tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=reach)
    return (dist.reshape(moved.shape[:2]) < reach).mean(axis=1)


def samples_the_surface(work: Working) -> bool:
    """Whether the entered target holds at least ``CLOSE_FIT_DENSITY`` times the working target's points: only then
    does :func:`close_fit` measure distances to the surface rather than to samples as sparse as the working ones."""
    return samples_densely(work.tgt_e, work.tgt_w)


def plane_frames_on_the_surface(work: Working) -> bool:
    """Whether both working clouds are built of orthogonal planes (:attr:`Working.plane_frame_rotations`) and the
    entered target samples their surface densely (:func:`samples_the_surface`): then any of the 24 frame rotations
    can overlay the source on walls and floor, and only the search's ranking of them tells a quarter- or half-turned
    room from the right one (``docs/decisions/0023-auto-searches-rooms.md``)."""
    return samples_the_surface(work) and work.plane_frame_rotations is not None


def rank_candidates(work: Working, starts: list[tuple[np.ndarray, np.ndarray]],
                    short_refine: Callable[[list[tuple[np.ndarray, np.ndarray]]], tuple[np.ndarray, np.ndarray]]
                    ) -> Ranked:
    """``short_refine`` the start poses (caller's units; it returns ``R [C, 3, 3]``, ``t [C, 3]``), rank the results
    by :func:`close_fit` where the entered target :func:`samples_the_surface`, then by inlier ratio and residual on
    the working clouds (:func:`service.rotation_search.rank_hypotheses`), and flag a close second elsewhere (by the
    fit that ranked them)."""
    rotations, translations = short_refine(starts)  # short refinements: enough to rank the basins
    order, ratios, _ = rank_hypotheses(work.working_source, work.tgt_w, rotations, translations, work.inlier_distance)
    fits, measure = candidate_fits(work, rotations, translations, ratios)  # [C]
    if measure == FIT_NAME:
        order = order[np.argsort(-fits[order], kind="stable")]
    pick = int(order[0])
    ambiguity = ranking_ambiguity(work, rotations, translations, fits, pick, measure=measure)
    return Ranked(pick, ambiguity, rotations[pick], translations[pick], rotations, translations, fits)


def settled_ambiguity(work: Working, ranked: Ranked, rotation: np.ndarray, translation: np.ndarray,
                      refine_full: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
                      most: int = 3) -> str | None:
    """The ranking's ambiguity once the winner has its full refinement (``rotation [3, 3]``, ``translation [3]``):
    the close seconds of the short ranking (at most ``most``) get the same full refinement (``refine_full``), and the
    ranking's own test (:func:`ranking_ambiguity`) is asked again of those poses; the warning goes where it then
    finds none (every close second in the winner's basin): two short refinements of one basin, stopped apart, are not
    two places that fit."""
    if ranked.ambiguity is None:
        return None
    fits, pick = ranked.fits, ranked.pick
    close = [int(i) for i in np.argsort(-fits, kind="stable")
             if i != pick and fits[i] >= fits[pick] - AMBIGUOUS_RATIO_GAP]
    if len(close) > most:
        return ranked.ambiguity
    rotations, translations = ranked.rotations.copy(), ranked.translations.copy()  # [C, 3, 3], [C, 3]
    rotations[pick], translations[pick] = rotation, translation
    for i in close:
        rotations[i], translations[i] = refine_full(rotations[i], translations[i])
    return ranked.ambiguity if ranking_ambiguity(work, rotations, translations, fits, pick) else None


def candidate_fits(work: Working, rotations: np.ndarray, translations: np.ndarray, ratios: np.ndarray | None = None
                   ) -> tuple[np.ndarray, str]:
    """``[C]`` the fit :func:`rank_candidates` ranks the poses (``rotations [C, 3, 3]``, ``translations [C, 3]``,
    caller's units) by -- :func:`close_fit` where the entered target :func:`samples_the_surface`, else the inlier
    ratio on the working clouds (``ratios [C]`` where the caller has them) -- and its name for warnings."""
    if samples_the_surface(work):
        return close_fit(work, rotations, translations), FIT_NAME
    if ratios is None:
        ratios = rank_hypotheses(work.working_source, work.tgt_w, rotations, translations, work.inlier_distance)[1]
    return ratios, "inlier ratio"


def ranking_ambiguity(work: Working, rotations: np.ndarray, translations: np.ndarray, fits: np.ndarray, best: int,
                      measure: str = "inlier ratio") -> str | None:
    """The warning of a ranking whose winner is ``best`` (``rotations [C, 3, 3]``, ``translations [C, 3]``, ``fits
    [C]``: the ``measure`` the warning names): a close second turned far from it
    (:func:`service.rotation_search.ambiguity_warning`), else one that places the source far from it
    (:func:`shift_ambiguity`)."""
    return (ambiguity_warning(rotations, fits, best, measure=measure)
            or shift_ambiguity(work, rotations, translations, fits, best, measure=measure))


def shift_ambiguity(work: Working, rotations: np.ndarray, translations: np.ndarray, fits: np.ndarray,
                    best: int, measure: str = "inlier ratio") -> str | None:
    """A warning when a candidate that places the working source's centroid more than ``AMBIGUOUS_SHIFT`` from where
    the winner ``best`` does fits almost as well (``rotations [C, 3, 3]``, ``translations [C, 3]``, ``fits [C]``: the
    ``measure`` the warning names)."""
    centre = work.working_source.mean(axis=0)  # [3] the working source's centroid, caller's frame
    placed = rotations @ centre + translations  # [C, 3]
    shift = np.linalg.norm(placed - placed[best], axis=1)  # [C] caller's units
    i = close_second(fits, best, shift > AMBIGUOUS_SHIFT * work.norm.scale)
    if i is None:
        return None
    return (f"{SHIFT_AMBIGUITY} {shift[i]:.3g} further {fits_as(fits[i], fits[best])} ({measure} "
            f"{fits[i]:.2f} vs {fits[best]:.2f}); the clouds may slide along flat or repeated surfaces")
