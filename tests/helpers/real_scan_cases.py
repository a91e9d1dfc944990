"""The real-scan development set and the bundled model ``general`` in tests: one case loaded and registered with the
service's defaults, ``general``'s normalisation radius.

Tests that use it skip with a reason when the set (``$MFGNET_REAL_DATA``, else ``../shared/data/real`` beside the
repository) or the bundled model ``general`` is absent.
"""

from __future__ import annotations

import dataclasses

import pytest

from bench.real_scans import Case, data_dir, load_cases, pose_errors, thresholds
from bench.turntable_scans import EFFECTS
from service.manifest import bundled_models_dir, load_manifest
from service.registrar import Registrar
from service.result import RegistrationResult

GENERAL = bundled_models_dir() / "general"


def skip_without_general() -> None:
    """Skips the calling test when the bundled model ``general`` is absent."""
    if not (GENERAL / "manifest.json").exists():
        pytest.skip("bundled model 'general' absent")


# The turntable scans as bench.turntable_scans made them before decision 0095 (random thinning, not a pixel grid): the
# cases the consensus and assess tests pin were measured on them.
THINNED_TURNTABLE = dataclasses.replace(EFFECTS, pixel_pitch=None)


def general_reference_radius() -> float:
    """``general``'s normalisation radius (its manifest): the inlier distance the stages judge by; skips without it."""
    skip_without_general()
    return float(load_manifest(GENERAL).normalization["reference_radius"])


def skip_without(pair: str) -> None:
    """Skips the calling test when ``pair`` of the real-scan set or the bundled model ``general`` is absent."""
    if not (data_dir() / f"{pair}.npz").exists():
        pytest.skip(f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")
    skip_without_general()


def real_case(pair: str, seed: int, variant: str, scale: float = 1.0) -> Case:
    """``pair``'s ``variant`` (``scanned``, ``turned``, ``turned-2``, ...) loaded alone at ``seed`` and ``scale``, as
    :func:`bench.real_scans.load_cases` makes it; skips without the set or the bundled model."""
    skip_without(pair)
    turns = int(variant.rpartition("-")[2]) if variant.startswith("turned-") else 1
    return next(c for c in load_cases(data_dir(), seed, (scale,), [pair], turns=turns) if c.variant == variant)


def register_with_defaults(case: Case) -> tuple[RegistrationResult, float, float]:
    """``case`` registered by ``general`` with the service's defaults: the result, its rotation error (degrees) and its
    translation error (the case's units)."""
    result = Registrar(GENERAL).register(case.source, case.target, refine="icp-plane", rotation_search="auto")
    return result, *pose_errors(result.rotation, result.translation, case.src_to_tgt)


def assert_registers(pair: str, seed: int, variant: str, scale: float = 1.0) -> RegistrationResult:
    """``pair``'s ``variant`` at ``seed`` and ``scale`` registers with the defaults, within the data README's
    thresholds; returns the result."""
    case = real_case(pair, seed, variant, scale)
    result, degrees, error = register_with_defaults(case)
    max_degrees, max_error = thresholds(case.sensor, scale)
    assert degrees < max_degrees and error < max_error, (degrees, error)
    return result
