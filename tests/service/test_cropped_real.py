"""A real range image cut to 60% of its points against its whole partner: the cut source is smaller than the
target, so the inlier distance (set by the source's size) fell below the working target's point spacing, the
density's attainable inlier ratio was 0, and a pose 134 deg off came back ``reliable``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from real_scan_cases import real_case, register_with_defaults

from bench.altered_scans import ALTERATIONS, altered
from bench.real_scans import thresholds


def test_a_cropped_range_image_is_not_called_reliable_when_wrong() -> None:
    case = real_case("dragon_72_24", 0, "scanned")
    rng = np.random.default_rng([ALTERATIONS.index("crop"), sum(map(ord, "dragon_72_24"))])
    source, target = altered("crop", case.source, case.target, rng)  # the source's 60% on one side of a plane
    result, degrees, error = register_with_defaults(replace(case, source=source, target=target))
    max_degrees, max_error = thresholds(case.sensor)
    right = degrees < max_degrees and error < max_error
    assert right or not result.reliable, (degrees, error, result.warnings)
