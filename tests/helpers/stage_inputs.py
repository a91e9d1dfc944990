"""What a stage test hands a stage: the working clouds as the pipeline's first stages make them, and a bare result."""

from __future__ import annotations

import numpy as np
from real_scan_cases import general_reference_radius

from service.options import RegistrationOptions
from service.result import RegistrationResult
from service.stages.normalise import Working, normalise
from service.stages.sample import sample
from service.stages.validate import validate


def working_clouds(source: np.ndarray, target: np.ndarray, options: dict | None = None, *,
                   reference_radius: float | None = None, iterations: int = 3, keypoints: int = 128
                   ) -> tuple[Working, RegistrationOptions]:
    """``source [N, 3]`` and ``target [M, 3]`` validated with the request ``options`` (default: ``refine:
    icp-plane``), sampled and normalised at ``reference_radius`` (default: ``general``'s), and the request's options."""
    request = validate(source, target, None, {"refine": "icp-plane"} if options is None else options, iterations,
                       keypoints)
    radius = general_reference_radius() if reference_radius is None else reference_radius
    return normalise(sample(request), radius), request.options


def result_at(R: np.ndarray, t: np.ndarray, *, reliable: bool = True, inlier_ratio: float = 1.0,
              residual_rms: float = 0.0, warnings: list[str] | None = None, iterations: int = 3,
              stability: float | None = None) -> RegistrationResult:
    """A result with pose ``R [3, 3], t [3]``, no correspondences and the quality figures given."""
    empty = np.zeros(0)
    return RegistrationResult(rotation=R, translation=t, source_index=empty.astype(np.int64),
                              target_index=empty.astype(np.int64), credibility=empty, weight=empty,
                              inlier_ratio=inlier_ratio, residual_rms=residual_rms, reliable=reliable,
                              warnings=[] if warnings is None else list(warnings), iterations=iterations,
                              timing_ms={}, stability=stability)
