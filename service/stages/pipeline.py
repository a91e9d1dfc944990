"""The stage functions a :class:`service.registrar.Registrar` runs, as one swappable record.

Replace one (``dataclasses.replace(Stages(), sample=my_sample)``, then ``Registrar(dir, stages=...)``) to insert
work before or after it -- e.g. a reduction of huge clouds wrapping ``sample`` -- with the same signature.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from service.stages.anchor import anchor
from service.stages.assess import assess_result
from service.stages.consensus import consensus
from service.stages.features import feature_candidates
from service.stages.fine import fine
from service.stages.flip import flip
from service.stages.float32_check import float32_check
from service.stages.free_space import free_space
from service.stages.guess import guess_candidate, unguessed_candidate
from service.stages.guess_check import guess_check
from service.stages.network import network
from service.stages.normalise import normalise
from service.stages.refine import refine
from service.stages.sample import sample
from service.stages.scale_check import scale_check
from service.stages.search import auto_search, search
from service.stages.slide import slide
from service.stages.symmetry import symmetry
from service.stages.unrefined_check import unrefined_check
from service.stages.validate import validate


@dataclass(frozen=True)
class Stages:
    validate: Callable = validate  # (source, target, options, overrides, iterations, keypoints) -> Request
    anchor: Callable = anchor  # (Request) -> (Request about the origin, Anchors back to the caller's frames)
    sample: Callable = sample  # (Request) -> Sampled
    normalise: Callable = normalise  # (Sampled, reference_radius) -> Working
    network: Callable = network  # (registrar, Working, iterations, keypoints, timing) -> Candidates
    guess: Callable = guess_candidate  # (Working, Candidates) -> more; where the caller gave an initial_transform
    # (registrar, Working, iterations, keypoints, timing) -> Candidates or None; where the result strayed from the guess
    unguessed: Callable = unguessed_candidate
    features: Callable = feature_candidates  # (registrar, Working, Candidates, iterations, keypoints, timing) -> more
    search: Callable = search  # (registrar, Working, hypotheses, iterations, keypoints, refine, timing, points=None)
    refine: Callable = refine  # (Working, starts, RegistrationOptions) -> Refined
    slide: Callable = slide  # (Working, Refined, RegistrationOptions) -> Refined
    flip: Callable = flip  # (Working, Refined, RegistrationOptions) -> Refined; after a search only
    assess: Callable = assess_result  # (Working, Candidates, Refined, iterations, return_iterations, timing, unrefined)
    # (solve, Working, plain, hypotheses, timing, retry_points, confirmed, guided, strayed) -> RegistrationResult
    auto_search: Callable = auto_search
    # (registrar, Working, RegistrationResult, RegistrationOptions, iterations, keypoints, timing) -> the same or the
    # descriptors' consensus pose; with rotation_search "auto", after its search
    consensus: Callable = consensus
    fine: Callable = fine  # (Working, RegistrationResult, RegistrationOptions, timing) -> RegistrationResult
    symmetry: Callable = symmetry  # (Working, RegistrationResult, RegistrationOptions, timing) -> RegistrationResult
    free_space: Callable = free_space  # (Working, RegistrationResult, RegistrationOptions, timing) -> the same
    # (Working, RegistrationResult, RegistrationOptions, timing) -> the same; refine "none": reliable if a short
    # refinement leaves the pose
    unrefined_check: Callable = unrefined_check
    guess_check: Callable = guess_check  # (Working, RegistrationResult, caller frames, Request, reference_radius)
    scale_check: Callable = scale_check  # (Working, RegistrationResult) -> the same, warned of a unit mismatch
    float32_check: Callable = float32_check  # (Working, RegistrationResult, Request) -> the same, warned of float32
