"""Stage 9, free space: a ``reliable`` result whose pose puts surface where a range image's sensor saw through is not.

Where either entered cloud is a range image (:attr:`service.stages.normalise.Working.range_views`), the final pose
moves the other cloud's fine points (:attr:`Working.fine_source`, :attr:`Working.fine_target`) into that image's
view; more than ``RELIABLE_FREE_SPACE`` of them in front of the surface its sensor saw
(:func:`service.free_space.pose_free_space`) takes ``reliable`` away, with a warning. The pose itself is kept. It runs
last, on the pose the caller gets (after the fine refinement), and only on a result still about to be called
``reliable`` (``docs/decisions/0053-free-space-of-range-images.md``).
"""

from __future__ import annotations

import dataclasses
import time

from service.free_space import pose_free_space
from service.options import RegistrationOptions
from service.result import RegistrationResult
from service.stages.normalise import Working

# Right poses on the real range images leave a few percent of the other scan in front of what a sensor saw; poses half
# a turn off, and low-overlap poses that overlay the clouds better than the truth, a tenth or more.
RELIABLE_FREE_SPACE = 0.08


def free_space_warning(work: Working, result: RegistrationResult) -> str | None:
    """A ``through free space`` warning where the pose of ``result`` puts more than ``RELIABLE_FREE_SPACE`` of one
    cloud's fine points where the other cloud's range-image sensor saw through, else ``None`` (also where neither
    cloud is a range image)."""
    source_view, target_view = work.range_views
    share = pose_free_space(source_view, target_view, work.fine_source, work.fine_target, result.rotation,
                            result.translation)
    if share is None or share <= RELIABLE_FREE_SPACE:
        return None
    return (f"through free space: {share:.3f} of one scan's points lie where the other scan's sensor saw through, "
            f"> {RELIABLE_FREE_SPACE}; a right pose puts surface only where a sensor saw surface or nothing")


def free_space(work: Working, result: RegistrationResult, options: RegistrationOptions,
               timing: dict[str, float]) -> RegistrationResult:
    """``result``, not ``reliable`` and with :func:`free_space_warning`'s warning where that applies; the time is
    added to ``timing["postprocess"]``."""
    if not result.reliable:
        return result
    started = time.perf_counter()
    warning = free_space_warning(work, result)
    timing["postprocess"] = timing.get("postprocess", 0.0) + 1000 * (time.perf_counter() - started)
    if warning is None:
        return result
    return dataclasses.replace(result, reliable=False, warnings=[*result.warnings, warning])
