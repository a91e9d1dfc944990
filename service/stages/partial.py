"""The partial-view check of ``rotation_search="auto"``: a plain result that fits poorly only because the clouds
overlap in part is not searched again.

A right pose of a partial view leaves the parts of the source that the target does not hold far from it and the
rest on its surface; a wrong pose that ICP pulled onto the target crosses its surface and leaves many points a
little off it. :func:`service.quality.near_surface_share` tells the two apart, except for one kind of wrong pose: a
near-symmetric shape turned 180 deg, which also lies on the target's surface where it overlaps. So the check also
turns the pose 180 deg about each principal axis of the moved source and keeps the search when a turned pose,
after the search's short ICP, fits almost as well (``docs/decisions/0011-partial-views-skip-the-search.md``).
"""

from __future__ import annotations

import numpy as np

from service.icp import icp_many
from service.quality import near_surface_share
from service.result import RegistrationResult
from service.rotation_search import SEARCH_ICP_DISTANCE, SEARCH_ICP_ITERATIONS, SEARCH_ICP_STRIDE, rank_hypotheses
from service.stages.normalise import Working

PARTIAL_NEAR_SHARE = 0.75  # lowest near-surface share of a partial view
PARTIAL_FLIP_RATIO = 0.9  # a turned pose fitting at least this share of the pose's inlier ratio is a doubt


def principal_frame(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centroid ``[3]`` and principal axes ``[3, 3]`` (rows, largest spread first) of ``points [N, 3]`` moved by
    the pose ``R [3, 3], t [3]``."""
    moved = points @ R.T + t  # [N, 3]
    centre = moved.mean(axis=0)  # [3]
    return centre, np.linalg.svd(moved - centre, full_matrices=False)[2]


def half_turns(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose ``R [3, 3], t [3]`` of ``points [N, 3]`` turned 180 deg about each principal axis of the moved points,
    through their centroid -> ``R [3, 3, 3], t [3, 3]``."""
    centre, axes = principal_frame(points, R, t)
    turns = 2.0 * axes[:, :, None] * axes[:, None, :] - np.eye(3)  # [3, 3, 3] half turns about each axis
    return turns @ R, (turns @ (t - centre)) + centre


def looks_partial(work: Working, result: RegistrationResult) -> bool:
    """Whether ``result`` (the plain pass's) looks like a right pose of a partial view: its near-surface share on the
    working clouds reaches ``PARTIAL_NEAR_SHARE`` and none of its :func:`half_turns`, after the search's short ICP,
    reaches ``PARTIAL_FLIP_RATIO`` of its inlier ratio."""
    src, tgt = work.working_source, work.tgt_w  # [Ns, 3] caller's frame, [Nt, 3]
    R, t = result.rotation, result.translation
    if near_surface_share(src, tgt, R, t, work.inlier_distance) < PARTIAL_NEAR_SHARE:
        return False
    R_h, t_h = icp_many(src[::SEARCH_ICP_STRIDE], tgt, *half_turns(src, R, t),
                        max_distance=SEARCH_ICP_DISTANCE * work.norm.scale, max_iterations=SEARCH_ICP_ITERATIONS)
    ratios = rank_hypotheses(src, tgt, np.concatenate([R[None], R_h]), np.concatenate([t[None], t_h]),
                             work.inlier_distance)[1]  # [4] the pose, then its turns
    return bool(ratios[1:].max() < PARTIAL_FLIP_RATIO * ratios[0])
