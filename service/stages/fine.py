"""Stage 7, fine: the final pose refined once more, on clouds denser than the working ones (coarse to fine).

The network and every refinement before this one work on the 768-point working clouds. On a dense scan those
samples lie far apart, and point-to-plane ICP against normals estimated from them stops a degree or more from the
truth (several millimetres on a range image). Where the caller's target is much denser than its working cloud
(:func:`service.stages.ranking.samples_the_surface`), reciprocal point-to-plane ICP (:func:`service.icp.icp_plane`)
moves up to ``PRECISE_SOURCE_POINTS`` points of the entered source (a uniform subsample;
:mod:`service.stages.normalise`) onto every point of the entered target, with the normals of the target points it
pairs, pairing points closer than one inlier distance (``docs/decisions/0018-fine-refinement-on-denser-clouds.md``,
``docs/decisions/0122-the-fine-stage-on-the-whole-target.md``).

It runs on the result the pipeline chose (after the rotation search's comparison), and again on a result the
descriptor consensus puts in its place (:mod:`service.stages.consensus`), and changes its pose only:
the result's quality (``inlier_ratio``, ``reliable``, warnings, stability) is what the pipeline measured on the
working clouds at the pose before it. A fine pose that moves a working source point more than ``FINE_MAX_MOVE``
inlier distances from that pose has left the basin those checks judged, and is not taken.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from service.icp import PLANE_MIN_INLIERS, LazySurface, icp_plane, rms_radius
from service.options import RegistrationOptions
from service.refine_modes import PLANE_MODES
from service.result import RegistrationResult
from service.stages.normalise import Working
from service.stages.ranking import samples_the_surface

FINE_ITERATIONS = 15  # most updates
FINE_TOLERANCE = 3e-4  # stop on updates below this (rad, x overlap_radius; 3e-4 rad is 0.017 deg)
FINE_MAX_MOVE = 3.0  # inlier distances: the farthest the fine pose may move a working source point


def applies(work: Working, options: RegistrationOptions) -> bool:
    """Whether the fine refinement runs: a point-to-plane refinement and a target dense enough that its working samples
    lie far apart, whatever ``refine_points`` asks: its clouds hold at most 8,192 of the target's points, and the
    fine stage pairs with every point of the entered target (decision 0122)."""
    return options.refine_mode in PLANE_MODES and samples_the_surface(work)


def fine_pose(work: Working, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The caller's pose ``R [3, 3], t [3]`` refined from :attr:`Working.precise_source` onto the entered target
    (:attr:`Working.entered_target_surface`), or ``None`` where that refinement stops early (a degenerate system, too
    few pairs: it warns) or moves a working source point more than ``FINE_MAX_MOVE`` inlier distances."""
    surface = work.entered_target_surface
    fitted = icp_plane(work.precise_source, surface.points, R, t, max_distance=work.inlier_distance,
                       max_iterations=FINE_ITERATIONS, tolerance=FINE_TOLERANCE, target_surface=surface,
                       point_fallback=False,  # a pose that warns is not taken: no point-to-point ICP of every point
                       scale=overlap_radius(work, surface, R, t))
    if fitted.warnings:
        return None
    moved = work.working_source @ (fitted.rotation - R).T + (fitted.translation - t)  # [Ns, 3] how far each point moves
    if np.sqrt((moved**2).sum(axis=1).max()) > FINE_MAX_MOVE * work.inlier_distance:
        return None
    return fitted.rotation, fitted.translation


def overlap_radius(work: Working, surface: LazySurface, R: np.ndarray, t: np.ndarray) -> float:
    """The RMS radius of the :attr:`Working.precise_source` points that lie within an inlier distance of the target at
    the pose ``R [3, 3], t [3]`` (all of them where fewer than ``PLANE_MIN_INLIERS`` do): the extent the pairs cover,
    which scales the refinement's normal equations. The whole target's radius, or the whole source's, grows with one
    point a kilometre out or a background beyond the overlap until every system looks degenerate, and the stage
    silently kept the coarser pose."""
    moved = work.precise_source @ R.T + t  # [Np, 3]
    near = np.isfinite(surface.tree.query(moved, k=1, distance_upper_bound=work.inlier_distance)[0])  # [Np]
    return rms_radius(work.precise_source[near] if near.sum() >= PLANE_MIN_INLIERS else work.precise_source)


def fine(work: Working, result: RegistrationResult, options: RegistrationOptions,
         timing: dict[str, float]) -> RegistrationResult:
    """``result`` with its pose refined by :func:`fine_pose` where :func:`applies` (else ``result`` itself); the time
    is added to ``timing["refine"]``."""
    if not applies(work, options):
        return result
    started = time.perf_counter()
    pose = fine_pose(work, result.rotation, result.translation)
    timing["refine"] = timing.get("refine", 0.0) + 1000 * (time.perf_counter() - started)
    if pose is None:
        return result
    return dataclasses.replace(result, rotation=pose[0], translation=pose[1])
