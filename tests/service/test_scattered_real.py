"""A real range image with scattered points added: registered, where the working clouds used to be a quarter
scattered points and the result came back 46 deg off as ``reliable``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from real_scan_cases import real_case, register_with_defaults

from bench.real_scans import thresholds


def test_a_range_image_with_a_tenth_more_scattered_points_registers() -> None:
    case = real_case("dragon_168_144", 0, "scanned")
    rng = np.random.default_rng([4, sum(map(ord, "dragon_168_144"))])

    def scattered(points: np.ndarray) -> np.ndarray:  # 10% more points, uniform in the cloud's bounding box
        extra = rng.uniform(points.min(axis=0), points.max(axis=0), size=(len(points) // 10, 3))
        return np.concatenate([points, extra]).astype(np.float32)

    case = replace(case, source=scattered(case.source), target=scattered(case.target))
    result, degrees, error = register_with_defaults(case)
    max_degrees, max_error = thresholds(case.sensor)
    assert degrees < max_degrees and error < max_error, (degrees, error, result.reliable)
