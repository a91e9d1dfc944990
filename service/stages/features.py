"""Stage 4a of ``rotation_search="auto"``: a candidate pose from matched local descriptors.

Where the plain network's pose overlays the target poorly (:func:`service.stages.search.plain_overlay` below
``SEARCH_AHEAD_BELOW``: a turned scan, mostly), a coarse pose from rotation-invariant descriptors
(:func:`service.feature_match.feature_pose`) joins the network's as a second candidate before the refinement, which
ranks both and refines the better one; where it overlays passably (below ``DESCRIBE_BELOW``), only once the refined
plain result looks wrong, before the search. Where enough matched pairs agree with it, the search is not started
ahead, and a result that then fits well, or that the feature pose confirms (:func:`feature_confirmed`), needs no
search at all (``docs/decisions/0034-a-feature-matched-candidate.md``, ``0035``, ``0036``).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from service.rotation_search import SearchCandidate, deferred_output, rotation_between_deg
from service.stages.network import Candidates
from service.stages.normalise import Working, to_caller
from service.stages.ranking import plane_frames_on_the_surface
from service.stages.search import search_rows

if TYPE_CHECKING:
    from service.registrar import Registrar
    from service.result import RegistrationResult

# Where the plain network's pose overlays at least 0.3 (SEARCH_AHEAD_BELOW) but less than this share of what a right
# pose reaches (service.stages.search.plain_overlay), auto tries the feature candidate after the plain pass, where its
# refined result looks wrong, before the search: on the 756 in-process real cases 3 more right and 29 fewer searched;
# thresholds of 0.4-0.6 gained the same (docs/decisions/0036-feature-candidates-before-the-search.md).
DESCRIBE_BELOW = 0.45
# Descriptors need a densely sampled surface: both entered clouds must hold at least this many times the working
# size. Scans do (15,000-65,000 points against 768 in the real-scan set); the ModelNet40 pairs (512-2,048 points) do
# not: on 680 simulated range scans of 512 points at any orientation the candidate changed no result.
DENSITY = 4
# A feature pose becomes a candidate when at least this many matched pairs agree with it: the refinement ranks it
# beside the network's pose. On the 756 in-process real cases 12 registered 3 more than 15 and called 11 more
# `reliable` (none wrong); 10 called two wrong derived cases `reliable`
# (docs/decisions/0048-feature-candidates-from-twelve-agreeing-pairs.md). On the 36 one-turn real cases the poses
# within 15 deg of the truth had 25-208 agreeing pairs but one (13), the others 6-18.
JOIN_SUPPORT = 12
# A feature pose confirms the refined result it agrees with (no search, feature_confirmed) when at least this many do.
MIN_SUPPORT = 15
# A refined result within this angle of the feature pose lies in its basin (the feature poses are coarse: the refined
# results that kept one lay 0.3-25 deg from it on the 756 in-process real cases, those that did not 55-179 deg). Not
# 30 deg: on turntable range images two wrong results lay 27 and 29 deg from a feature pose; searched, both came right
# (docs/decisions/0074-a-confirmation-within-25-degrees.md).
AGREEMENT_DEG = 25.0


def describable(work: Working) -> bool:
    """Whether :func:`feature_candidates` computes descriptors for ``work``: both entered clouds hold ``DENSITY``
    times the working size, and they are not rooms (:func:`service.stages.search.plane_frames_on_the_surface`:
    ``auto`` searches their plane frames whatever the plain pass gives)."""
    return dense_enough_to_describe(work) and not plane_frames_on_the_surface(work)


def dense_enough_to_describe(work: Working) -> bool:
    """Whether both entered clouds hold ``DENSITY`` times the working size: their surface is sampled densely enough
    for the descriptors."""
    return min(len(work.src_e), len(work.tgt_e)) >= DENSITY * max(len(work.src_w), len(work.tgt_w))


def feature_candidate(registrar: Registrar, work: Working, rotation: np.ndarray, translation: np.ndarray,
                      iterations: int, keypoints: int, timing: dict[str, float], key: str) -> SearchCandidate:
    """The caller's pose ``rotation [3, 3], translation [3]`` (a feature pose) as a candidate between the normalised
    clouds, with the network's output from its rotation on the search's rows (its correspondences, should it win;
    remapped to the working rows), computed only where it is read, its time added to ``timing[key]``."""
    rotation, translation = work.norm.normalize_pose(rotation, translation)
    sub_s, sub_t, kp = search_rows(registrar, work, keypoints, short_icp=True)
    output = deferred_output(registrar.start_network, work.src_n[sub_s], work.tgt_n[sub_t], rotation, iterations, kp,
                             timing, key, rows=(sub_s, sub_t))  # keypoints as working rows
    return SearchCandidate(output, rotation, rotation, translation)


def feature_candidates(registrar: Registrar, work: Working, found: Candidates, iterations: int, keypoints: int,
                       timing: dict[str, float]) -> Candidates:
    """``found`` (the plain network's candidate) and, where the clouds are :func:`describable` and ``JOIN_SUPPORT``
    matched pairs agree with it, the feature pose of the entered clouds (in the initial guess's frame), normalised,
    with the network's output from its rotation on the search's rows (its correspondences, should it win; remapped to
    the working rows), computed only where it is read. Records ``timing["features"]`` where it computed descriptors
    (and adds that network pass's time to it, should it run)."""
    if not describable(work):
        return found
    started = time.perf_counter()
    pose = work.feature_pose  # of the entered source after the initial guess
    if pose is None or pose.support < JOIN_SUPPORT:
        timing["features"] = 1000 * (time.perf_counter() - started)
        return found
    candidate = feature_candidate(registrar, work, pose.rotation, pose.translation, iterations, keypoints, timing,
                                  "features")
    timing["features"] = 1000 * (time.perf_counter() - started)
    return Candidates([*found.poses, candidate], found.net_s, found.net_t, feature_support=pose.support)


def feature_confirmed(work: Working, found: Candidates, result: RegistrationResult) -> bool:
    """Whether a feature candidate joined ``found`` (:func:`feature_candidates`: ``MIN_SUPPORT`` matched pairs agree
    with it) and the refined ``result`` (caller's frame) lies within ``AGREEMENT_DEG`` of its rotation: the descriptors'
    consensus and the refinement's fit point to the same pose, which ``auto`` then does not search
    (``docs/decisions/0035-no-search-after-a-confirmed-feature-pose.md``)."""
    if found.feature_support < MIN_SUPPORT:
        return False
    candidate = found.poses[-1]
    rotation, _ = to_caller(work, candidate.rotation, candidate.translation)
    return rotation_between_deg(rotation, result.rotation) < AGREEMENT_DEG
