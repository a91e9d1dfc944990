"""Stage 8, free space: a ``reliable`` result whose pose puts surface where a range image's sensor saw through is not.

Where either entered cloud is a range image (:attr:`service.stages.normalise.Working.range_views`), the final pose moves
the other cloud's fine points (:attr:`Working.fine_source`, :attr:`Working.fine_target`) into that image's view; more
than ``RELIABLE_FREE_SPACE`` of them in front of the surface its sensor saw (:func:`service.free_space.pose_free_space`)
takes ``reliable`` away, with a warning. Conversely, a result that only the doubts free space settles
(``SETTLED_DOUBTS``) kept from ``reliable`` is ``reliable`` where at most ``CONFIRMS_BELOW`` lie there and at least
``CONFIRMS_SEEING`` where a sensor saw at all, both clouds being range images: two range images that overlap in part
overlay each other loosely, and a pose only the second, denser rotation search found is not half a turn off if it leaves
the sensors' free space clear. Beside one range image alone that is no evidence: a pose half a turn off about an axis
across its view lays the other scan on or behind the surface it saw, where its free space holds nothing (a scanned
toilet so turned left 0.014 of it in front). A confirmation reads :attr:`Working.confirming_views`, where a range image
with range noise has a view read over more neighbours (then at most ``COARSE_CONFIRMS_BELOW``). The pose itself is kept.
It runs on the pose the caller gets (after the fine refinement), before the symmetry check, which still judges a
confirmed result (``docs/decisions/0053-free-space-of-range-images.md``,
``docs/decisions/0054-free-space-settles-the-second-search.md``,
``docs/decisions/0094-free-space-through-range-noise-and-thinning.md``,
``docs/decisions/0096-free-space-confirms-between-two-range-images.md``).
"""

from __future__ import annotations

import dataclasses
import time

from service.free_space import COARSE_VIEW_NEIGHBOURS, PoseFreeSpace, RangeView, pose_free_space
from service.options import RegistrationOptions
from service.quality import LOOSE_FIT  # the warning it overrules (quality.assess, stages.assess.off_the_surface)
from service.result import RegistrationResult
from service.stages.normalise import Working
from service.stages.search import RETRY_WARNING  # the other doubt it settles
from service.stages.withdraw import CONFIRMED_BY_FREE_SPACE, withdrawn

# Right poses on the real range images leave a few percent of the other scan in front of what a sensor saw; wrong ones
# 0.038 and more, and those the other checks left `reliable` (half a turn off, or low-overlap poses that overlay the
# clouds better than the truth) a tenth or more.
RELIABLE_FREE_SPACE = 0.08
# ... and a pose that leaves at most this share there, where only SETTLED_DOUBTS kept it from `reliable`, is: right
# low-overlap range images overlay each other loosely at 0.014 and less; wrong poses that fit loosely put 0.059 and
# more there (the derived dragon pairs at 10 turns), each with another doubt besides.
CONFIRMS_BELOW = 0.03
# ... where at least this share of one scan's points lies in cells the other's sensor saw: below it, half-turned poses
# of the set's dragon pairs (full, thinned, with noise) mostly leave under CONFIRMS_BELOW there too, whatever the pose
# (docs/decisions/0094)
CONFIRMS_SEEING = 0.1
# ... and at most this share where a view read over COARSE_VIEW_NEIGHBOURS takes part: its wider cells and tolerance
# leave less of a wrong pose in front (true poses of noisy and thinned dragon pairs 0.010 at most, half-turned ones
# seeing a tenth 0.015 and more; turns of 120-165 deg can leave less; docs/decisions/0094)
COARSE_CONFIRMS_BELOW = 0.01
# The warnings free space settles: a loose fit, and a pose found by the second, denser search only (0028: a few such
# were half a turn off; on the real range images right ones leave at most 0.010 in free space, wrong ones 0.038 and
# more, each with another doubt besides).
SETTLED_DOUBTS = (LOOSE_FIT, RETRY_WARNING)
# The kind (the text before the colon) of the doubt this stage adds (its note: withdraw.CONFIRMED_BY_FREE_SPACE)
THROUGH_FREE_SPACE = "through free space"


def free_space_of(work: Working, result: RegistrationResult,
                  views: tuple[RangeView | None, RangeView | None]) -> PoseFreeSpace | None:
    """The shares of one cloud's fine points that the pose of ``result`` puts where the other cloud's range-image
    sensor saw through and where it saw at all (each the larger of the two ways), or ``None`` where neither cloud is
    a range image; ``views``: the source's and the target's (:attr:`Working.range_views` or
    :attr:`Working.confirming_views`)."""
    source_view, target_view = views
    if source_view is None and target_view is None:
        return None  # before the fine points are asked for: they are built only where they are used
    return pose_free_space(source_view, target_view, work.fine_source, work.fine_target, result.rotation,
                           result.translation)


def only_settled_doubts(result: RegistrationResult) -> bool:
    """Whether every warning of ``result`` (at least one) is one of ``SETTLED_DOUBTS``."""
    return bool(result.warnings) and all(w.startswith(SETTLED_DOUBTS) for w in result.warnings)


def confirms_below(views: tuple[RangeView | None, RangeView | None]) -> float:
    """The share of one scan in the other's free space up to which ``views`` confirm a pose: ``CONFIRMS_BELOW``, or
    ``COARSE_CONFIRMS_BELOW`` where a view read over ``COARSE_VIEW_NEIGHBOURS`` takes part."""
    coarse = any(view is not None and view.neighbours == COARSE_VIEW_NEIGHBOURS for view in views)
    return COARSE_CONFIRMS_BELOW if coarse else CONFIRMS_BELOW


def free_space(work: Working, result: RegistrationResult, options: RegistrationOptions,
               timing: dict[str, float]) -> RegistrationResult:
    """``result`` judged by its free space (:func:`free_space_of`): a ``reliable`` one with more than
    ``RELIABLE_FREE_SPACE`` is not, with a ``through free space`` warning; one that only ``SETTLED_DOUBTS`` kept
    from ``reliable`` is, judged by :attr:`Working.confirming_views` where both are views, with at most
    :func:`confirms_below` where at least ``CONFIRMS_SEEING`` lie where a sensor saw (its warnings stay, and a note says
    so). The time is added to ``timing["postprocess"]``."""
    if not (result.reliable or only_settled_doubts(result)):
        return result
    started = time.perf_counter()
    views = work.range_views if result.reliable else work.confirming_views
    one_view_confirms_nothing = not result.reliable and None in views
    shares = None if one_view_confirms_nothing else free_space_of(work, result, views)
    timing["postprocess"] = timing.get("postprocess", 0.0) + 1000 * (time.perf_counter() - started)
    if shares is None:
        return result
    if result.reliable and shares.share > RELIABLE_FREE_SPACE:
        return withdrawn(result, through_free_space(shares.share))
    bound = confirms_below(views)
    if not result.reliable and shares.share <= bound and shares.seen >= CONFIRMS_SEEING:
        return dataclasses.replace(result, reliable=True,
                                   warnings=[*result.warnings, confirmed_by_free_space(shares.share, bound)])
    return result


def through_free_space(share: float) -> str:
    """The warning of a result that puts ``share`` (> ``RELIABLE_FREE_SPACE``) of a scan in a sensor's free space."""
    return (f"{THROUGH_FREE_SPACE}: {share:.3f} of one scan's points lie where the other scan's sensor saw through, "
            f"> {RELIABLE_FREE_SPACE}; a right pose puts surface only where a sensor saw surface or nothing")


def confirmed_by_free_space(share: float, bound: float = CONFIRMS_BELOW) -> str:
    """The note of a result made ``reliable`` by leaving at most ``bound`` (``share``) in free space."""
    return (f"{CONFIRMED_BY_FREE_SPACE}: only {share:.3f} of one scan's points lie where the other scan's sensor saw "
            f"through, <= {bound}; range images that overlap in part overlay each other loosely, and a pose "
            "half a turn off would put surface there")
