"""Stage 4 with ``rotation_search``: the network from many start rotations -> the best few candidate poses;
and ``rotation_search="auto"``: search only when the plain result looks wrong, keep the better of both."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from service.network_loop import NetworkLoop
from service.plane_frames import overlap_scores
from service.result import RegistrationResult
from service.rotation_search import (
    SEARCH_KEEP,
    SearchCandidate,
    deferred_output,
    distinct_candidates,
    rank_hypotheses,
    search_hypotheses,
)
from service.sampling import evenly_spaced_indices
from service.speculation import Speculation
from service.stages.assess import off_the_surface, poor_fit
from service.stages.network import Candidates
from service.stages.normalise import INLIER_DISTANCE, Working, to_caller
from service.stages.partial import looks_partial
from service.stages.ranking import plane_frames_on_the_surface
from service.stages.slide import overlaid_share

if TYPE_CHECKING:
    from service.registrar import Registrar

# rotation_search="auto" searches when the plain result's inlier ratio is below this share of the ratio a
# right pose can reach at the target's density (service.quality.attainable_inlier_ratio). Chosen on the
# bundled `general` model with refine="icp-plane" (docs/decisions/0002-rotation-search-default-and-trigger.md):
# right poses reach 0.93-0.98 of it on dense and sparse pairs alike; at 0.8 "auto" matched the former fixed
# threshold (inlier ratio 0.7) on dense pairs at 45/90/180 deg and on sparse pairs searched 5% instead of 77%
# of 300 pairs within 45 deg (recall at 5 deg 0.860 vs 0.870), with equal or better recall at 90 and 180 deg.
# Only the relative rule decides: the former extra "or not reliable" searched 3 more of those 300 pairs
# (targets too sparse to reach the reliable ratio at all) and made one worse.
AUTO_SEARCH_RELATIVE_RATIO = 0.8
# After the search of rotation_search="auto", a result that still fits poorly (its inlier ratio below what the
# `reliable` rule asks, service.quality) is searched again on RETRY_SEARCH_POINTS rows per cloud (the default working
# clouds whole), where the model searches a smaller subsample (service.rotation_search.SEARCH_POINTS) and the clouds
# are not rooms built of orthogonal planes (their search starts from the plane frames): on 128 points the network
# from none of the 24 starts reached the right basin of some turned range images that it reaches on more
# (docs/decisions/0028). A pose only the second search finds is not `reliable`: 24 of 32 such were right; on range
# images the free-space stage can confirm it (service.stages.free_space).
RETRY_SEARCH_POINTS = 768
RETRY_WARNING = ("found by the second, denser rotation search only (the first fitted poorly): not reliable unless "
                 "the scans' free space confirms it")
# rotation_search="auto" starts its search beside the plain pass (service.speculation) where the plain network's pose,
# before any refinement, overlays fewer working source points than this share of the ratio a right pose can reach:
# on the real-scan cases the plain pass then nearly always asks for the search (docs/decisions/0029).
SEARCH_AHEAD_BELOW = 0.3


def search(registrar: Registrar, work: Working, hypotheses: np.ndarray, iterations: int, keypoints: int,
           refine: str, timing: dict[str, float], points: int | None = None) -> Candidates:
    """:func:`service.rotation_search.search_hypotheses` from the start rotations ``hypotheses [H, 3, 3]``, or with
    a refinement, where both working clouds are built of orthogonal planes, the :func:`plane_frame_starts` instead.

    With a refinement (``refine != "none"``) every hypothesis gets a short point-to-point ICP, a model whose
    manifest has a ``search`` section searches that many rows spread through each working cloud with at most that
    many keypoints, and every distinct kept candidate is returned (the refine stage ranks them again); without
    one, only the search's best. ``points``: that many rows per cloud instead of the manifest's (the second search of
    :func:`auto_search`). Records ``timing["encoder"]`` (the target, embedded once; not from plane frames, whose
    network pass waits for the winner) and the search's keys.
    """
    short_icp = refine != "none"  # point-to-point for every refine mode (docs/DESIGN.md)
    tic = time.perf_counter()
    starts = plane_frame_starts(work) if short_icp else None
    sub_s, sub_t, keypoints = search_rows(registrar, work, keypoints, short_icp, points)
    src_n, tgt_n = work.src_n[sub_s], work.tgt_n[sub_t]  # [Ns', 3], [Nt', 3]
    if starts is not None:
        candidates = plane_frame_candidates(registrar.start_network, src_n, tgt_n, starts, iterations, keypoints,
                                            timing)
        timing["search"] = 1000 * (time.perf_counter() - tic)
        timing["search_per_hypothesis"] = timing["search"] / len(starts)
        return Candidates(candidates, work.idx_s[sub_s], work.idx_t[sub_t])
    network = partial(registrar.start_network, target=registrar.embed_cloud(tgt_n))  # target embedded once
    timing["encoder"] = 1000 * (time.perf_counter() - tic)
    candidates = search_hypotheses(network, src_n, tgt_n, hypotheses, iterations, keypoints, short_icp,
                                   INLIER_DISTANCE, timing)
    # with a refinement every distinct kept candidate is refined and the refined poses ranked again
    candidates = distinct_candidates(candidates) if short_icp else candidates[:1]
    return Candidates(candidates, work.idx_s[sub_s], work.idx_t[sub_t])


def search_rows(registrar: Registrar, work: Working, keypoints: int, short_icp: bool, points: int | None = None
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """The rows of the working source and target ``([Ns'], [Nt'])`` the search runs the network on, and its keypoints:
    with a refinement after it (``short_icp``) and a manifest ``search`` section, that many rows spread through each
    cloud (``points`` instead, where given) and at most that many keypoints; else every row and ``keypoints``."""
    sub_s, sub_t = np.arange(len(work.src_n)), np.arange(len(work.tgt_n))
    subsample = registrar.manifest.search_subsample
    if subsample and points:
        subsample = (points, subsample[1])
    if short_icp and subsample:  # the refinement restores the precision: search a subsample
        sub_s, sub_t = (evenly_spaced_indices(len(c), subsample[0]) for c in (work.src_n, work.tgt_n))
        keypoints = min(keypoints, subsample[1], len(sub_s), len(sub_t))
    return sub_s, sub_t, keypoints


def plane_frame_starts(work: Working, keep: int = SEARCH_KEEP) -> np.ndarray | None:
    """``[keep, 3, 3]``: the rotations between the working clouds' dominant plane frames
    (:func:`service.plane_frames.frame_rotations`) that overlay the clouds best on a coarse grid
    (:func:`service.plane_frames.overlap_scores`), best first; ``None`` unless both clouds have such a frame."""
    rotations = work.plane_frame_rotations  # [24, 3, 3] or None
    if rotations is None:
        return None
    scores = overlap_scores(work.src_n, work.tgt_n, rotations)  # [24]
    return rotations[np.argsort(-scores, kind="stable")[:keep]]


def plane_frame_candidates(start_network: Callable[..., NetworkLoop], src_n: np.ndarray, tgt_n: np.ndarray,
                           starts: np.ndarray, iterations: int, keypoints: int, timing: dict[str, float]
                           ) -> list[SearchCandidate]:
    """The ``starts [S, 3, 3]`` as candidate poses (centroids together; the refine stage tries each rotation at its
    best translations too), each with the network's output from that start on ``src_n [N, 3]``, ``tgt_n [M, 3]``
    (its correspondences, should it win), computed only where it is read (:func:`deferred_output`, its time added to
    ``timing["search"]``): the starts are already within a few degrees of a right rotation, where the network,
    trained on single objects, can turn a room fragment away from it, so only the winner's correspondences need it
    (``docs/decisions/0056-network-passes-only-for-the-winner.md``)."""
    return [SearchCandidate(deferred_output(start_network, src_n, tgt_n, start, iterations, keypoints, timing,
                                            "search"), start, start, np.zeros(3)) for start in starts]


def needs_search(result: RegistrationResult, attainable_ratio: float = 1.0) -> bool:
    """Whether ``rotation_search="auto"`` searches after the plain ``result``: its inlier ratio is below
    ``AUTO_SEARCH_RELATIVE_RATIO`` times ``attainable_ratio`` (:func:`service.quality.attainable_inlier_ratio`
    of the working target). The registrar never searches degenerate clouds (:attr:`Working.searchable`)."""
    return result.inlier_ratio < AUTO_SEARCH_RELATIVE_RATIO * attainable_ratio


def looks_wrong(work: Working, plain: RegistrationResult, guided: bool = False) -> bool:
    """Whether ``auto`` doubts the ``plain`` result (see :func:`auto_search`): it fits poorly and is not a partial
    view's, both clouds are rooms over a dense target (unless ``guided``: the result keeps the caller's guess,
    :func:`service.stages.guess.keeps_guess`, which tells a room's frame rotations apart), or a result that is not
    ``reliable`` lies off the target's surface."""
    return ((needs_search(plain, work.attainable_ratio) and not looks_partial(work, plain))
            or (plane_frames_on_the_surface(work) and not guided)
            # a reliable result has passed off_the_surface already
            or (not plain.reliable and off_the_surface(work, plain.rotation, plain.translation) is not None))


def auto_search(solve: Callable[..., RegistrationResult], work: Working, plain: RegistrationResult,
                hypotheses: np.ndarray, timing: dict[str, float], retry_points: int | None = None,
                confirmed: bool = False, guided: bool = False, strayed: bool = False) -> RegistrationResult:
    """``plain`` unless, on non-degenerate clouds, it may be wrong (:func:`looks_wrong`): it fits poorly
    (:func:`needs_search`) and is not a partial view's (:func:`service.stages.partial.looks_partial`); or it lies off a
    dense target's surface
    (:func:`service.stages.assess.off_the_surface`: the inlier-ratio test misses wrong poses where the working
    clouds are sparser than the inlier distance, as a LiDAR scan's are); or both clouds are built of orthogonal
    planes over a dense target (:func:`plane_frames_on_the_surface`: a room turned by a quarter or half turn can
    lie on the target's walls and floor). Then ``solve(hypotheses, {})`` (the pipeline with the search) and whichever
    final pose :func:`rank_hypotheses` ranks first (the plain one on a tie), with the plain pass's stage timings.
    If that still fits poorly (:func:`service.stages.assess.poor_fit`), ``retry_points`` is given
    (:func:`retry_points`) and the clouds are not rooms (:attr:`Working.plane_frame_rotations`),
    ``solve(hypotheses, {}, points=retry_points)`` searches again on that many points per cloud, and its pose, should
    it rank first, comes back not ``reliable`` with ``RETRY_WARNING``. A ``confirmed`` result (a feature pose agrees
    with it, :func:`service.stages.features.feature_confirmed`) is not searched, nor a ``guided`` one (it keeps the
    caller's guess, :func:`service.stages.guess.keeps_guess`) for being a room's alone; a ``strayed`` one is searched
    whatever its fit: it does not keep the caller's guess, and the network's pose from the caller's own frame, refined
    alone, lies elsewhere, fits worse and looks wrong, so the request without the guess would search
    (``Registrar.beside_unguessed``): a wrong basin reached from a wrong guess can fit well enough to pass the tests
    above (``docs/decisions/0068-the-unguessed-start-competes.md``).
    Records ``timing`` ``search`` (the whole second pass) and ``search_per_hypothesis`` when it searched."""
    if not work.searchable or confirmed or not (strayed or looks_wrong(work, plain, guided)):
        return plain
    started = time.perf_counter()
    result = better_of(work, plain, solve(hypotheses, {}), timing)
    # rooms (both clouds of orthogonal planes) search from their plane frames: a denser search gained none there
    if retry_points and poor_fit(work, result.inlier_ratio) and work.plane_frame_rotations is None:
        again = better_of(work, result, solve(hypotheses, {}, points=retry_points), timing)
        if again is not result:  # only the denser search found it
            again.reliable, again.warnings = False, [*again.warnings, RETRY_WARNING]
        result = again
    timing["search"] = 1000 * (time.perf_counter() - started)
    timing["search_per_hypothesis"] = timing["search"] / len(hypotheses)
    return result


def plain_overlay(work: Working, found: Candidates) -> float:
    """How well the plain pass's candidates (the network's pose, and the caller's guess where one was given: stage
    ``guess``), before any refinement, overlay the target: the larger share of working source points they bring within
    an inlier distance, over the share a right pose reaches at the target's density (:attr:`Working.attainable_ratio`);
    ``inf`` where that is 0 (nothing to judge) or the clouds are degenerate (never searched). Below
    ``SEARCH_AHEAD_BELOW`` ``auto`` tries a feature candidate in the plain pass and starts its search ahead; below
    :data:`service.stages.features.DESCRIBE_BELOW`, where the refined plain result looks wrong (:func:`looks_wrong`),
    it tries a feature candidate before the search."""
    if not work.searchable or work.attainable_ratio <= 0:
        return math.inf
    shares = (overlaid_share(work, *to_caller(work, pose.rotation, pose.translation)) for pose in found.poses)
    return max(shares) / work.attainable_ratio


def searched_ahead(solve: Callable[..., RegistrationResult], ahead: Speculation | None
                   ) -> Callable[..., RegistrationResult]:
    """``solve`` (``(hypotheses, timing, points=None)``, the pipeline with the search), except that the first search
    (no ``points``) is the one ``ahead`` ran where it was started (the same hypotheses, so the same result)."""
    if ahead is None:
        return solve

    def solve_or_wait(hypotheses: np.ndarray, timing: dict[str, float], points: int | None = None
                      ) -> RegistrationResult:
        return ahead.result() if points is None else solve(hypotheses, timing, points=points)

    return solve_or_wait


def better_of(work: Working, kept: RegistrationResult, other: RegistrationResult, timing: dict[str, float]
              ) -> RegistrationResult:
    """Whichever of ``kept`` and ``other`` :func:`rank_hypotheses` ranks first on the working clouds (``kept`` on a
    tie); ``other`` then carries ``timing`` (the plain pass's stage timings)."""
    rotations = np.stack([kept.rotation, other.rotation])  # [2, 3, 3] kept first: it wins ties
    translations = np.stack([kept.translation, other.translation])  # [2, 3]
    order = rank_hypotheses(work.working_source, work.tgt_w, rotations, translations, work.inlier_distance)[0]
    if order[0] == 0:
        return kept
    other.timing_ms = timing
    return other


def retry_points(subsample: tuple[int, int] | None) -> int | None:
    """``RETRY_SEARCH_POINTS`` where the model searches a subsample of fewer rows (its manifest's
    ``search_subsample``), else ``None``: a model that searches the full working clouds has nothing denser to try."""
    return RETRY_SEARCH_POINTS if subsample and subsample[0] < RETRY_SEARCH_POINTS else None
