"""Stage 11, scale check: a warning where the clouds' sizes differ as clouds of one scene in two units do.

The pose is rigid: it moves the source and keeps its size. Two scans of one scene in millimetres and in metres differ
in size by 1000x (centimetres 100x, inches 39x), and no rigid pose lays one on the other; such a request fails with
warnings of a poor fit or a low overlap that do not say why. Where the working clouds' RMS radii differ by
``UNITS_RATIO`` or more, the result carries a warning naming both sizes. The pose and ``reliable`` stay as they are:
a small scan registered into a far larger one (a frame into a map) may be right. It runs last, beside the guess check.
"""

from __future__ import annotations

import dataclasses

from service.normalization import rms_radius
from service.quality import IDENTICAL
from service.result import RegistrationResult
from service.stages.normalise import Working

# Sizes this many times apart: inches against metres (39x) and more. Pairs of one sensor differ far less (the working
# clouds of the development set's 18 pairs by at most 1.20x); a frame against a map many times its size may reach it,
# and only gets the warning.
UNITS_RATIO = 30.0
# A cloud of one repeated point has a radius of its centroid's rounding, which no unit explains: its own warning
# (``quality.degeneracy_warnings``: "source identical: ...") says what is wrong, and no size is compared
ONE_POINT = (f"source {IDENTICAL}", f"target {IDENTICAL}")
# The kind (the text before the colon) of the warning this stage adds
SIZE_MISMATCH = "size mismatch"


def scale_check(work: Working, result: RegistrationResult) -> RegistrationResult:
    """``result`` with :func:`size_mismatch`'s warning first where the working clouds' RMS radii differ by
    ``UNITS_RATIO`` or more (the poor fit, low overlap, sparse target or symmetric shape warned before it follow from
    it); else ``result`` itself. The pose and ``reliable`` are kept."""
    if any(warning.startswith(ONE_POINT) for warning in result.warnings):
        return result
    source, target = rms_radius(work.src_w), rms_radius(work.tgt_w)
    if max(source, target) < UNITS_RATIO * min(source, target):
        return result
    return dataclasses.replace(result, warnings=[size_mismatch(source, target), *result.warnings])


def size_mismatch(source: float, target: float) -> str:
    """The warning of clouds whose RMS radii are ``source`` and ``target`` (the clouds' units)."""
    larger, smaller = ("source", "target") if source > target else ("target", "source")
    ratio = max(source, target) / min(source, target)
    return (f"{SIZE_MISMATCH}: the {larger}'s RMS radius is {ratio:.0f}x the {smaller}'s ({max(source, target):.4g} "
            f"against {min(source, target):.4g}); if the clouds are in different units (millimetres against metres: "
            "1000x), convert one to the other's: the pose is rigid and keeps the source's size")
