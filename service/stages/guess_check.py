"""Stage 10, guess check: a warning where the result lies far from the caller's ``initial_transform``.

The guess is one candidate among the network's and the search's (stage ``guess``,
``docs/decisions/0037-the-callers-guess-as-a-candidate.md``): where another fits better, the answer leaves the guess
without a word, and a caller whose prior is wrong (most often given the wrong way round, ``T_source_target`` where
``T_target_source`` is asked for) would not learn it. So a result far from the guess (``FAR_DEG``, ``FAR_SHIFT``)
carries a warning saying how far; where it lies near the guess's inverse instead (``INVERSE_DEG``, ``FAR_SHIFT``),
the warning says the guess looks given target-to-source and should be inverted. The pose and ``reliable`` stay as
they are. It runs last, on the pose in the caller's frames.

Translations are compared where the two poses put the source's centroid (its anchor, :mod:`service.stages.anchor`),
not as the poses' ``t``: those differ by ``dR @ origin`` for any turn ``dR`` between them, so their gap would grow
with how far the caller's frame origin lies from the clouds.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from service.checks import check_transform
from service.result import RegistrationResult
from service.rotation_search import rotation_between_deg
from service.stages.normalise import Working
from service.stages.validate import Request

# A result more than this far from the guess, in rotation, is far from it: odometry and a previous frame's pose miss by
# a few degrees (decision 0037 models them 5-10 deg off), a room's other frame rotations lie 90 deg or more away, and
# a gap of 20 deg is a disagreement on the turn itself, not on its last degrees.
FAR_DEG = 20.0
# ... or in translation, more than this share of the source's RMS radius (the size the normalisation scales to the
# model's reference radius, so the rule holds in any units): a quarter of the cloud's size is no odometry drift. The
# same tolerance says whether the result lies near the guess's inverse.
FAR_SHIFT = 0.25
# A far result within this angle of the guess's inverse (and within FAR_SHIFT of where it puts the source's centroid)
# lies near that inverse: the guess was most likely given the other way round.
INVERSE_DEG = 5.0
# The kind (the text before the colon) of the warning this stage adds
FAR_FROM_GUESS = "far from initial transform"
# ... and of its warning on an unrefined result that is the guess as given and not reliable
GUESS_RETURNED = "initial transform returned"
# A result within this angle and this share of the source's RMS radius of the guess is the guess as given (a refined
# result always moves; an unrefined one is the guess where it fitted better than the network's pose from it)
AS_GIVEN_DEG = 1e-4
AS_GIVEN_SHIFT = 1e-6


@dataclasses.dataclass(frozen=True)
class GuessGap:
    """How far a result lies from a guess: rotation angle (deg) and translation at the source's centroid (caller's
    units)."""

    degrees: float
    shift: float


def pose_gap(R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray, centroid: np.ndarray) -> GuessGap:
    """The gap between the ``src_to_tgt`` poses ``R_a [3, 3], t_a [3]`` and ``R_b, t_b``: the angle of the turn
    between them and the distance between where each puts ``centroid [3]`` (the source's, caller's frame)."""
    shift = float(np.linalg.norm((R_a @ centroid + t_a) - (R_b @ centroid + t_b)))
    return GuessGap(rotation_between_deg(R_a, R_b), shift)


def source_size(work: Working, reference_radius: float) -> float:
    """The source's RMS radius (caller's units): ``work.norm.scale`` is it divided by ``reference_radius``
    (:meth:`service.normalization.Normalization.fit`; the target's where the source has none)."""
    return work.norm.scale * reference_radius


def guess_check(work: Working, result: RegistrationResult, request: Request,
                reference_radius: float) -> RegistrationResult:
    """``result`` (caller's frames) with :func:`far_from_guess`'s warning where the caller gave an
    ``initial_transform`` and the result lies more than ``FAR_DEG`` or ``FAR_SHIFT`` of the source's size
    (:func:`source_size`) from it, or :func:`guess_returned`'s where an unrefined result (``refine: "none"``) that is
    not ``reliable`` is the guess as given (within ``AS_GIVEN_DEG`` and ``AS_GIVEN_SHIFT`` of the source's size);
    else ``result`` itself. The pose and ``reliable`` are kept."""
    guess = request.options.initial_transform
    if guess is None:
        return result
    R_g, t_g = check_transform(guess)  # [3, 3], [3]: T_target_source, caller's frames, as the validate stage read it
    centroid = request.src_anchor  # [3] caller's source frame
    size = source_size(work, reference_radius)
    tolerance = FAR_SHIFT * size
    gap = pose_gap(result.rotation, result.translation, R_g, t_g, centroid)
    if gap.degrees <= FAR_DEG and gap.shift <= tolerance:
        as_given = gap.degrees <= AS_GIVEN_DEG and gap.shift <= AS_GIVEN_SHIFT * size
        if as_given and not result.reliable and request.options.refine_mode == "none":
            return dataclasses.replace(result, warnings=[*result.warnings, guess_returned()])
        return result
    inverse = pose_gap(result.rotation, result.translation, R_g.T, -R_g.T @ t_g, centroid)
    near_inverse = inverse.degrees <= INVERSE_DEG and inverse.shift <= tolerance
    warning = far_from_guess(gap, tolerance, inverse if near_inverse else None)
    return dataclasses.replace(result, warnings=[*result.warnings, warning])


def far_from_guess(gap: GuessGap, tolerance: float, inverse: GuessGap | None = None) -> str:
    """The warning of a result ``gap`` from the caller's guess (``tolerance``: ``FAR_SHIFT`` of the source's size,
    caller's units); ``inverse``: its gap from the guess's inverse, where it lies near it."""
    text = (f"{FAR_FROM_GUESS}: the result lies {gap.degrees:.1f} deg and {gap.shift:.4g} (the clouds' units, at the "
            f"source's centroid) from initial_transform (far: > {FAR_DEG:g} deg or > {tolerance:.4g}, "
            f"{FAR_SHIFT:g} of the source's RMS radius); the guess was not kept")
    if inverse is None:
        return text + "; check the prior (its frames and units), or leave it out"
    return (text + f", but the result lies within {inverse.degrees:.1f} deg and {inverse.shift:.4g} of its inverse: "
            "initial_transform looks given target-to-source (T_source_target); invert it and pass T_target_source, "
            "which takes source points into the target's frame")


def guess_returned() -> str:
    """The warning of an unrefined result that is the caller's guess as given and not ``reliable``: the prior itself
    may be what is wrong."""
    return (f"{GUESS_RETURNED}: the result is initial_transform as given (with refine: none it fitted better than the "
            "network's pose from it) and is not reliable; if the prior may be wrong, leave it out or refine (refine: "
            "icp-plane)")
