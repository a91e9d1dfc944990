"""Stage 5, refine: ICP (point-to-point or point-to-plane) of the network's pose in the caller's units.

With several candidates (the rotation search) each, and each one's rotation at its best candidate translations
(:func:`service.stages.ranking.with_translations`), first gets a short refinement -- the refinement's stages with
at most ``CANDIDATE_ITERATIONS`` updates each -- and they are ranked again, by their close fit to a dense target
(:mod:`service.stages.ranking`); the winner gets the full refinement, then ``icp-plane-multistart`` tries turned
starts (:func:`service.multistart.multistart`). Without a refinement the network's pose is returned as it is, or the
caller's guess where its basin fits better (:func:`unrefined_pick`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from service.icp import IcpResult, Surface, icp, refine_plane
from service.icp_batch import refine_plane_many
from service.multistart import multistart
from service.options import RegistrationOptions
from service.stages.normalise import ICP_DISTANCE, Working
from service.stages.ranking import rank_candidates, settled_ambiguity, with_translations

CANDIDATE_ITERATIONS = 3  # updates per stage of each search candidate's short refinement


@dataclass(frozen=True, eq=False)
class Refined:
    rotation: np.ndarray  # [3, 3] final src_to_tgt (caller's units)
    translation: np.ndarray  # [3]
    pick: int  # which start won (0 without a search)
    warnings: tuple[str, ...]  # the refinement's own (e.g. a degenerate system kept the previous pose)
    ambiguity: str | None  # the candidate ranking's ambiguity warning
    surface: Surface | None  # the refinement's target surface (icp-plane modes), reused by the assessment


def refine_pose(
    work: Working,
    R0: np.ndarray,
    t0: np.ndarray,
    refine: str,
    distance: float,
    max_iterations: int,
    surface: Surface | None,
    short: bool = False,
) -> IcpResult:
    """``refine`` (``icp`` or the point-to-plane stages of ``icp-plane*``) of the caller's pose ``R0, t0``, moving
    ``src_r`` (``short``: :attr:`Working.short_points`, every ``SHORT_REFINE_STRIDE``-th of its points)."""
    src = work.short_points if short else work.src_r
    if refine == "icp":
        return icp(src, work.tgt_r, R0, t0, max_distance=distance, max_iterations=max_iterations)
    own = work.short_surface if short else work.source_surface
    return refine_plane(
        src,
        work.tgt_r,
        R0,
        t0,
        max_distance=distance,
        max_iterations=max_iterations,
        target_surface=surface,
        source_surface=own,
    )


def short_refine(
    work: Working,
    starts: list[tuple[np.ndarray, np.ndarray]],
    refine: str,
    distance: float,
    surface: Surface | None,
    iterations: int = CANDIDATE_ITERATIONS,
) -> tuple[np.ndarray, np.ndarray]:
    """The candidates' short refinements, enough to rank basins: ``refine`` of each start pose (caller's units) with at
    most ``iterations`` (``CANDIDATE_ITERATIONS``) updates per stage, moving :attr:`Working.short_points`; the
    point-to-plane modes refine every start at once (:func:`service.icp_batch.refine_plane_many`). Returns
    ``R [C, 3, 3]``, ``t [C, 3]``."""
    if refine == "icp":
        basins = [refine_pose(work, R0, t0, refine, distance, iterations, None, short=True) for R0, t0 in starts]
        return np.stack([b.rotation for b in basins]), np.stack([b.translation for b in basins])
    rotations, translations = np.stack([R for R, _ in starts]), np.stack([t for _, t in starts])  # [C, 3, 3], [C, 3]
    return refine_plane_many(
        work.short_points,
        work.tgt_r,
        rotations,
        translations,
        max_distance=distance,
        max_iterations=iterations,
        target=surface,
        source=work.short_surface,
    )


def icp_distance(work: Working, options: RegistrationOptions) -> float:
    """The refinement's correspondence distance in the caller's units: ``icp_max_distance`` or ``ICP_DISTANCE``."""
    return options.icp_max_distance if options.icp_max_distance is not None else ICP_DISTANCE * work.norm.scale


def refine(work: Working, starts: list[tuple[np.ndarray, np.ndarray]], options: RegistrationOptions) -> Refined:
    """The refined pose from the candidate ``starts`` (caller's units, best first); ``refine="none"``: the first, or
    where the caller's guess is among them, the better fit of the two unrefined (:func:`unrefined_pick`)."""
    mode = options.refine_mode
    if mode == "none":
        return unrefined_pick(work, starts)
    scale = work.norm.scale
    distance = icp_distance(work, options)
    surface = work.target_surface if mode != "icp" else None  # one target surface for every stage
    pick, ambiguity, (R, t) = 0, None, starts[0]
    if len(starts) > 1:  # search candidates: a short refinement of each, ranked, then the winner's full one
        short = partial(short_refine, work, refine=mode, distance=distance, surface=surface)
        poses, origin = with_translations(work, starts)  # each candidate's rotation at other translations too
        ranked = rank_candidates(work, poses, short)
        pick, ambiguity, R, t = origin[ranked.pick], ranked.ambiguity, ranked.rotation, ranked.translation
    refined = refine_pose(work, R, t, mode, distance, options.icp_max_iterations, surface)
    if ambiguity is not None and options.initial_transform is not None:
        # the caller's guess among the candidates: judged again on full refinements, short ones only rank the basins
        # (docs/decisions/0108-a-guess-ranked-apart-from-its-own-basin.md)
        def refine_full(R_c: np.ndarray, t_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            full = refine_pose(work, R_c, t_c, mode, distance, options.icp_max_iterations, surface)
            return full.rotation, full.translation

        ambiguity = settled_ambiguity(work, ranked, refined.rotation, refined.translation, refine_full)
    if mode == "icp-plane-multistart":
        refined = multistart(work.src_r, work.tgt_r, refined, scale, distance, options.icp_max_iterations, surface)
    return Refined(refined.rotation, refined.translation, pick, refined.warnings, ambiguity, surface)


def unrefined_pick(work: Working, starts: list[tuple[np.ndarray, np.ndarray]]) -> Refined:
    """``refine="none"``: the network's (or the search's) pose ``starts[0]``; where the caller's guess follows it, the
    one of the two nearer the basin that fits best (:func:`nearest_start`), returned as it is: the network, started
    from a guess at the truth, can leave it 8-63 deg on real scans
    (``docs/decisions/0117-an-unrefined-guess-competes.md``)."""
    if len(starts) == 1:
        return Refined(*starts[0], pick=0, warnings=(), ambiguity=None, surface=None)
    # at the default correspondence distance: refine "none" refuses icp_max_distance (it sets a refinement)
    short = partial(short_refine, work, refine="icp-plane", distance=ICP_DISTANCE * work.norm.scale,
                    surface=work.target_surface)
    ranked = rank_candidates(work, starts, short)
    pick = nearest_start(work, starts, ranked.rotation, ranked.translation)
    return Refined(*starts[pick], pick, warnings=(), ambiguity=ranked.ambiguity, surface=None)


def nearest_start(work: Working, starts: list[tuple[np.ndarray, np.ndarray]], rotation: np.ndarray,
                  translation: np.ndarray) -> int:
    """Which of the ``starts`` (caller's units) places the short points nearest (RMS) where the pose ``rotation
    [3, 3]``, ``translation [3]`` does: the best basin's short refinement, ranked as the refinement ranks its
    candidates (:func:`service.stages.ranking.rank_candidates`). Two starts in one basin are told apart by which lies
    nearer its bottom, not by where their short refinements stopped."""
    points = work.short_points  # [S, 3] caller's frame
    goal = points @ rotation.T + translation  # [S, 3]
    apart = [np.sqrt(np.mean(np.sum((points @ R.T + t - goal) ** 2, axis=1))) for R, t in starts]
    return int(np.argmin(apart))  # the first on a tie
