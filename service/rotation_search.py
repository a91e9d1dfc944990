"""Rotation search: registration at any relative rotation, not only within the network's trained range.

The normalised working source starts from every rotation of a finite group covering SO(3) evenly
(:func:`search_rotations_for`); :func:`search_hypotheses` runs them through the registrar's network loop in
batches, optionally gives each pose a short wide-basin ICP (then only the best few after the first iteration
run the remaining ones), and returns the best few by :func:`rank_hypotheses` (inlier ratio, then residual); with
a refinement the registrar refines each distinct one briefly and ranks them again (:func:`distinct_candidates`).
``Registrar.register(rotation_search=True)`` calls it, and ``rotation_search="auto"`` when the plain result
looks wrong; figures and the reason for the short ICPs: ``docs/ROTATION_SEARCH.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
from scipy.spatial.transform import Rotation

from service.errors import InputError
from service.icp import icp_many
from service.kdtree import KDTree
from service.network_loop import DeferredOutput, NetworkLoop, NetworkOutput
from service.quality import inlier_statistics

SEARCH_GROUPS = {24: "O", 60: "I"}  # rotation-search sizes: the cube's (octahedral) / icosahedral group
# refine="icp" with the rotation search: each hypothesis first gets a short, wide-basin ICP (plain
# point-to-point, no mutual check, normalised distance cap) so that the ranking compares basins
SEARCH_ICP_DISTANCE = 0.3  # normalised units (3x registrar.ICP_DISTANCE)
SEARCH_ICP_ITERATIONS = 20
# The short ICPs move every SEARCH_ICP_STRIDE-th working source point (a spread subsample: the working cloud is
# in farthest-point or coordinate order), 3x cheaper; the ranking then scores each hypothesis on all points.
SEARCH_ICP_STRIDE = 3
# The hypotheses go through the network this many at a time: ONNX Runtime keeps each session's arena at the
# largest batch it has run, and all 24 at once grew the process by ~1.2 GB, 4 at a time by ~180 MB
# (docs/decisions/0002-rotation-search-default-and-trigger.md, "Alternatives measured"); 8 at a time took 0.96-1.0x
# the time of 4 (docs/decisions/0012-search-on-128-points.md). The caller embeds the target once for all of them.
SEARCH_BATCH = 4
# With the short ICPs, every hypothesis goes through the first SEARCH_PRUNE_ITERATIONS network iterations and its
# short ICP; only the SEARCH_KEEP best by rank_hypotheses go on through the remaining iterations (each exactly as
# without pruning) and their own short ICPs, and all of them are returned (docs/ROTATION_SEARCH.md, step 3).
# On real scans the first iteration often ranks the right basin below 4th place: 8 kept register 71 instead of 68
# of the 90 development cases (4 turns per pair) in process (docs/decisions/0010-eight-search-candidates.md).
SEARCH_PRUNE_ITERATIONS = 1
SEARCH_KEEP = 8
# The manifest's "search" section that the export writes for models trained on independently sampled pairs
# (service.manifest.Manifest.search_subsample): when a refinement follows, the search runs on SEARCH_POINTS rows
# spread evenly through each working cloud (service.sampling.evenly_spaced_indices) with SEARCH_KEYPOINTS
# keypoints; it only has to find the basin, and the refinement of the winner on the full clouds restores the
# precision. With `general` on 320 seeded independent-sample pairs at 90-180 deg the searched pairs cost 2-5x
# less at the same or a higher success rate; the paper-protocol models (shared points) lost pairs on a
# subsample and keep the full clouds (docs/decisions/0002-rotation-search-default-and-trigger.md). 128 rather than
# 256 points: more real-scan development cases registered, at the cost of dense complete shapes turned up to 180 deg
# (docs/decisions/0012-search-on-128-points.md).
SEARCH_POINTS = 128
SEARCH_KEYPOINTS = 32
# Kept candidates whose poses lie this close to a better one are not refined again (the same basin).
DUPLICATE_DEGREES = 1.0
DUPLICATE_DISTANCE = 0.01  # normalised units
# After the candidates' short refinements: another candidate more than AMBIGUOUS_DEGREES from the winner whose
# inlier ratio is within AMBIGUOUS_RATIO_GAP of the winner's makes the result ambiguous (not reliable, a warning).
# On 400 seeded searched pairs at 90 and 180 deg such results were wrong 36 times of 49; wrong results called
# reliable 86 -> 59, right ones called unreliable 0 -> 13 of 289
# (docs/decisions/0003-reliable-rule-and-stability-threshold.md, rule 4).
AMBIGUOUS_DEGREES = 10.0
AMBIGUOUS_RATIO_GAP = 0.03


@cache
def search_rotations_for(count: int) -> np.ndarray:
    """The ``count`` initial rotations ``[H, 3, 3]`` of the rotation search (read-only).

    A finite rotation group covering SO(3) evenly, deterministic on every machine: 24 = the
    rotation group of the cube (every rotation is within 62.8 degrees of one of them), 60 = the
    icosahedral group (within 44.5 degrees).
    """
    if count not in SEARCH_GROUPS:
        raise InputError(f"search_rotations must be one of {sorted(SEARCH_GROUPS)}, got {count}")
    rotations = Rotation.create_group(SEARCH_GROUPS[count]).as_matrix()  # [H, 3, 3]
    rotations.setflags(write=False)
    return rotations


def rank_hypotheses(
    src_n: np.ndarray, tgt_n: np.ndarray, rotations: np.ndarray, translations: np.ndarray, inlier_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order of the poses ``rotations [H, 3, 3]``, ``translations [H, 3]`` of ``src_n [N, 3]`` onto ``tgt_n``.

    Best first: highest inlier ratio at ``inlier_distance``, ties by the lower inlier RMS residual,
    then by index. Returns the order ``[H]``, inlier ratios ``[H]`` and residuals ``[H]``.
    """
    moved = src_n.astype(np.float64) @ rotations.transpose(0, 2, 1) + translations[:, None]  # [H, N, 3]
    dist, _ = KDTree(tgt_n).query(moved.reshape(-1, 3), k=1, distance_upper_bound=2 * inlier_distance)
    ratio, rms = inlier_statistics(dist.reshape(moved.shape[:2]), inlier_distance)  # [H], [H]
    return np.lexsort((np.arange(len(ratio)), rms, -ratio)), ratio, rms


@dataclass(frozen=True, eq=False)  # compared by identity (array fields)
class SearchCandidate:
    """A hypothesis the search kept: its network output (or one computed when first read, :func:`deferred_output`),
    start rotation and pose of the searched (normalised) source onto the target, after its short ICP when the
    search ran them."""

    network: NetworkOutput | DeferredOutput
    start: np.ndarray  # [3, 3] start rotation
    rotation: np.ndarray  # [3, 3] network pose composed after the start (and the short ICP)
    translation: np.ndarray  # [3]

    @property
    def output(self) -> NetworkOutput:
        """The network's output from :attr:`start` (its correspondences, iteration poses), computed here if deferred."""
        return self.network.get() if isinstance(self.network, DeferredOutput) else self.network


def search_hypotheses(
    start_network: Callable[..., NetworkLoop],
    src_n: np.ndarray,
    tgt_n: np.ndarray,
    hypotheses: np.ndarray,
    iterations: int,
    keypoints: int,
    short_icp: bool,
    inlier_distance: float,
    timing: dict[str, float],
) -> list[SearchCandidate]:
    """The best starts of ``src_n [N, 3]`` (float32, normalised) rotated by each of ``hypotheses [H, 3, 3]``.

    ``start_network`` (``Registrar.start_network``, with the target's embedding bound) encodes the ``H`` rotated
    sources against ``tgt_n`` in batches of ``SEARCH_BATCH``; each hypothesis's pose is its network pose composed
    after its start rotation. ``short_icp``: every pose first gets a short wide-basin ICP (``SEARCH_ICP_*``) and
    the ranking uses those poses; then only the ``SEARCH_KEEP`` best after ``SEARCH_PRUNE_ITERATIONS`` network
    iterations run the remaining ones (without ``short_icp`` every hypothesis runs them all).
    Returns the ``SEARCH_KEEP`` best candidates by :func:`rank_hypotheses`, best first (the caller refines them and
    ranks again: the short ICPs on a subsample leave wrong basins ahead of the right one);
    records ``timing["search"]`` (the whole search) and ``timing["search_per_hypothesis"]``.
    """
    started = time.perf_counter()
    prune = short_icp and len(hypotheses) > SEARCH_KEEP and iterations > SEARCH_PRUNE_ITERATIONS
    first = SEARCH_PRUNE_ITERATIONS if prune else iterations
    loop, starts = network_from(start_network, src_n, tgt_n, hypotheses, first, keypoints, timing), hypotheses
    if prune:
        keep = rank_hypotheses(src_n, tgt_n, *_search_poses(loop, starts, src_n, tgt_n), inlier_distance)[0]
        keep = keep[:SEARCH_KEEP]
        loop, starts = loop.select(keep), hypotheses[keep]
        loop.advance(iterations, timing, batch=SEARCH_BATCH)
    R_h, t_h = _search_poses(loop, starts, src_n, tgt_n) if short_icp else (loop.rotation @ starts, loop.translation)
    order = rank_hypotheses(src_n, tgt_n, R_h, t_h, inlier_distance)[0][:SEARCH_KEEP]
    outputs = loop.outputs()
    timing["search"] = 1000 * (time.perf_counter() - started)
    timing["search_per_hypothesis"] = timing["search"] / len(hypotheses)
    return [SearchCandidate(outputs[i], starts[i], R_h[i], t_h[i]) for i in order]


def network_from(start_network: Callable[..., NetworkLoop], src_n: np.ndarray, tgt_n: np.ndarray,
                 starts: np.ndarray, iterations: int, keypoints: int, timing: dict[str, float]) -> NetworkLoop:
    """The network loop of ``src_n [N, 3]`` turned by each of ``starts [H, 3, 3]`` against ``tgt_n``, after
    ``iterations``: ``SEARCH_BATCH`` starts per ``start_network`` call (bounded ONNX Runtime arenas)."""
    src_h = (src_n.astype(np.float64) @ starts.transpose(0, 2, 1)).astype(np.float32)  # [H, N, 3]
    batches = []
    for first in range(0, len(starts), SEARCH_BATCH):
        batch = start_network(src_h[first : first + SEARCH_BATCH], tgt_n, keypoints, timing, same_source=True)
        batch.advance(iterations, timing)
        batches.append(batch)
    return NetworkLoop.join(batches)


def deferred_output(start_network: Callable[..., NetworkLoop], src_n: np.ndarray, tgt_n: np.ndarray,
                    start: np.ndarray, iterations: int, keypoints: int, timing: dict[str, float], key: str,
                    rows: tuple[np.ndarray, np.ndarray] | None = None) -> DeferredOutput:
    """The network's output from ``start [3, 3]`` on ``src_n [N, 3]``, ``tgt_n [M, 3]`` (:func:`network_from`),
    computed only when first read, its time then added to ``timing[key]``; ``rows``: the source's and target's rows
    ``([N], [M])`` its keypoints are given as."""
    def compute() -> NetworkOutput:
        tic = time.perf_counter()
        output = network_from(start_network, src_n, tgt_n, start[None], iterations, keypoints, {}).outputs()[0]
        if rows is not None:
            output = replace(output, src_kp=rows[0][output.src_kp], tgt_kp=rows[1][output.tgt_kp])
        timing[key] = timing.get(key, 0.0) + 1000 * (time.perf_counter() - tic)
        return output

    return DeferredOutput(compute)


def distinct_candidates(candidates: list[SearchCandidate]) -> list[SearchCandidate]:
    """``candidates`` without those whose pose lies within ``DUPLICATE_DEGREES`` and ``DUPLICATE_DISTANCE``
    (normalised) of an earlier one: they would refine to the same pose."""
    kept: list[SearchCandidate] = []
    for c in candidates:
        if not any(_same_pose(c, k) for k in kept):
            kept.append(c)
    return kept


def _same_pose(a: SearchCandidate, b: SearchCandidate) -> bool:
    return bool(rotation_between_deg(a.rotation, b.rotation) < DUPLICATE_DEGREES
                and np.linalg.norm(a.translation - b.translation) < DUPLICATE_DISTANCE)


def rotation_between_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in degrees of the rotation taking ``R_a [3, 3]`` to ``R_b [3, 3]``."""
    cos = np.clip((np.trace(R_a.T @ R_b) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def ambiguity_warning(rotations: np.ndarray, ratios: np.ndarray, best: int, measure: str = "inlier ratio"
                      ) -> str | None:
    """A warning when a pose far from the best one fits almost as well: ``rotations [H, 3, 3]`` and fits ``[H]``
    (inlier ratios, or the ``measure`` the warning names) of the ranked candidates, ``best`` the winner's row.
    Symmetric or near-symmetric shapes leave the pose undetermined; the winner is then wrong more often than right
    (docs/ROTATION_SEARCH.md)."""
    angles = np.array([rotation_between_deg(rotations[best], R) for R in rotations])  # [H]
    i = close_second(ratios, best, angles > AMBIGUOUS_DEGREES)
    if i is None:
        return None
    return (f"ambiguous: a pose {angles[i]:.0f} deg away {fits_as(ratios[i], ratios[best])} ({measure} "
            f"{ratios[i]:.2f} vs {ratios[best]:.2f}); the shape may be symmetric")


def fits_as(other: float, best: float) -> str:
    """How a close second's fit ``other`` compares with the kept pose's ``best``, in an ambiguity warning: a check
    after the ranking (the symmetry check's refined turns) can find one that fits better."""
    other, best = round(float(other), 2), round(float(best), 2)  # as the warning prints them
    return "fits better" if other > best else "fits as well" if other == best else "fits almost as well"


def close_second(ratios: np.ndarray, best: int, far: np.ndarray) -> int | None:
    """The best-fitting candidate other than ``best`` among those marked ``far [H]`` whose fit (``ratios [H]``: inlier
    ratios or close fits) is within ``AMBIGUOUS_RATIO_GAP`` of the winner's, or ``None``."""
    for i in np.argsort(-ratios, kind="stable"):
        if i != best and far[i] and ratios[i] >= ratios[best] - AMBIGUOUS_RATIO_GAP:
            return int(i)
    return None


def _search_poses(loop: NetworkLoop, starts: np.ndarray, src_n: np.ndarray, tgt_n: np.ndarray):
    """Each hypothesis's pose of ``src_n`` so far (network pose after its start rotation), moved by the short ICP:
    ``R [H, 3, 3]``, ``t [H, 3]`` (rank refined poses: the basin matters, not the raw pose)."""
    return icp_many(
        src_n[::SEARCH_ICP_STRIDE], tgt_n, loop.rotation @ starts, loop.translation,
        max_distance=SEARCH_ICP_DISTANCE, max_iterations=SEARCH_ICP_ITERATIONS,
    )
