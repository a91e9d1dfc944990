"""Stage 12, float32 check: a warning where a cloud's coordinates are float32 values far enough from the origin that
float32 rounds them coarsely.

float32 keeps 24 bits: at 5,000,000 (a UTM northing in metres) its step is 0.5, so a scan stored as float32 in map
coordinates has lost its shape to a half-metre grid before the service sees it, and the pose comes out degrees off,
sometimes `reliable`. Where a cloud's working points are all float32 values (so the file or array held float32) and
float32's step at their largest coordinate is at least ``STEP_SHARE`` of the cloud's RMS radius, the result carries a
warning naming the distance, the step and what to send instead; so does a cloud of float16 values at least
``FAR_OUT_RADII`` RMS radii out (its step 8,192 times float32's). The pose stays, and ``reliable`` as it is but where
the step reaches ``UNRELIABLE_STEP_SHARE`` of a warned cloud's RMS radius (its shape lost to the grid). Clouds
in float64 (JSON, float64 ``.npy`` or PLY/PCD doubles, LAS's scaled integers) or near the origin do not get it, but
for whole numbers far out on float16's grid, which the values cannot tell from float16 (the warning says so).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from service.normalization import rms_radius
from service.result import RegistrationResult
from service.stages.normalise import Working
from service.stages.validate import Request

# float32's step at the largest coordinate, as a share of the cloud's RMS radius, from which the warning is given: a
# LiDAR frame 10 m across at a UTM northing (step 0.5 m) is 5% off its grid; one 1 km from the origin (step 6e-5 m)
# is not warned.
STEP_SHARE = 1e-3
# float32's step as a share of the RMS radius from which the cloud's shape is lost to the grid and the result is not
# reliable (decision 0120)
UNRELIABLE_STEP_SHARE = 0.13
# float16 values are warned only this many RMS radii or more from the origin, where an offset would keep their digits
FAR_OUT_RADII = 10.0
# float16 holds every whole number up to this; beyond it a whole-number cloud may be float16's rounding itself
FLOAT16_WHOLE = 2048.0
# The kind (the text before the colon) of the warning this stage adds
FLOAT32_ROUNDING = "float32 rounding"


def float32_check(work: Working, result: RegistrationResult, request: Request) -> RegistrationResult:
    """``result`` with :func:`float32_rounding`'s warning for each cloud whose working points (in the caller's values,
    ``request.src[work.idx_s]``) are all float32 values and lie far enough out that float32's step there reaches
    ``STEP_SHARE`` of the cloud's RMS radius, or all float16 values far out (:func:`coarse_float`); else ``result``
    itself. The pose is kept, and ``reliable`` but where the step reaches ``UNRELIABLE_STEP_SHARE`` of such a cloud's
    RMS radius."""
    warnings, coarse = [], False
    for name, points in (("source", request.src[work.idx_s]), ("target", request.tgt[work.idx_t])):  # [Nw, 3]
        if (dtype := coarse_float(points)) is None:
            continue
        largest, radius = float(np.abs(points).max()), rms_radius(points)
        flattened = float(np.spacing(dtype(largest))) >= UNRELIABLE_STEP_SHARE * radius
        warnings.append(float32_rounding(name, largest, radius, dtype,
                                         whole=bool(np.array_equal(points, np.round(points))), flattened=flattened))
        coarse |= flattened
    if not warnings:
        return result
    return dataclasses.replace(result, warnings=[*result.warnings, *warnings],
                               reliable=result.reliable and not coarse)


def coarse_float32(points: np.ndarray) -> bool:
    """Whether ``points [N, 3]`` (float64) are all float32 values and float32's step at their largest coordinate is
    at least ``STEP_SHARE`` of their RMS radius."""
    step = float(np.spacing(np.float32(np.abs(points).max())))
    radius = rms_radius(points)
    if radius <= 0 or step < STEP_SHARE * radius:
        return False
    return bool(np.array_equal(points, points.astype(np.float32).astype(np.float64)))


def coarse_float(points: np.ndarray) -> type | None:
    """``np.float16`` where ``points [N, 3]`` (float64) are all float16 values, not all whole numbers up to
    ``FLOAT16_WHOLE`` (integer data float16 holds exactly), that lie at
    least ``FAR_OUT_RADII`` RMS radii out where float16's step reaches ``STEP_SHARE`` of the radius (a float16 array
    far out: its step is 8,192 times float32's, 0.0156 at 16), else ``np.float32`` where :func:`coarse_float32` holds,
    else ``None``. About the origin float16 holds any cloud to about 0.1% of its radius, its format's own precision,
    which no offset mends: such clouds (ModelNet40 as stored) are not warned."""
    largest, radius = float(np.abs(points).max()), rms_radius(points)
    if (radius > 0 and FAR_OUT_RADII * radius <= largest <= float(np.finfo(np.float16).max)
            and float(np.spacing(np.float16(largest))) >= STEP_SHARE * radius
            and np.array_equal(points, points.astype(np.float16).astype(np.float64))
            and not (largest <= FLOAT16_WHOLE and np.array_equal(points, np.round(points)))):
        return np.float16
    return np.float32 if coarse_float32(points) else None


def float32_rounding(name: str, largest: float, radius: float, dtype: type = np.float32, whole: bool = False,
                     flattened: bool = False) -> str:
    """The warning of cloud ``name`` whose largest coordinate is ``largest`` and RMS radius ``radius``, its values
    those of ``dtype`` (``np.float32`` or ``np.float16``); ``whole``: all whole numbers, which beyond 2,048 may as well
    be a grid of whole numbers as coarse as float16's (the values cannot tell); ``flattened``: the step reaches
    ``UNRELIABLE_STEP_SHARE`` of the radius, and the warning says the result is not reliable for it."""
    step = float(np.spacing(dtype(largest)))
    kind = np.dtype(dtype).name
    values = f"{kind} values" if not (whole and dtype is np.float16) else "whole numbers on float16's grid (float16 " \
        "values, or a grid as coarse)"
    unreliable = f"; at {UNRELIABLE_STEP_SHARE:.0%} or more of the radius the result is not reliable" * flattened
    return (f"{FLOAT32_ROUNDING}: the {name}'s coordinates are {values} up to {largest:.4g} from the origin, "
            f"where {kind} holds them to {step:.3g} ({step / radius:.2%} of its RMS radius {radius:.4g}); send "
            "float64 coordinates (JSON, a float64 .npy, PLY or PCD doubles) or subtract an offset first (a map origin)"
            + unreliable)
