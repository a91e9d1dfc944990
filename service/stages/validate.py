"""Stage 1, validate: the caller's clouds and options -> a checked :class:`Request` (or ``InputError``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from service.checks import check_cloud, check_transform
from service.options import RegistrationOptions
from service.rotation_search import search_rotations_for


@dataclass(frozen=True, eq=False)
class Request:
    """One checked registration request."""

    src: np.ndarray  # [N, 3] float64, the caller's source (its own array where it was float64): read, never written
    tgt: np.ndarray  # [M, 3] float64, the caller's target, the same
    options: RegistrationOptions
    iterations: int  # the model's default filled in
    keypoints: int
    R_init: np.ndarray  # [3, 3] initial src_to_tgt guess (identity without one)
    t_init: np.ndarray  # [3]
    hypotheses: np.ndarray | None  # [H, 3, 3] the rotation search's starts; None when it never runs
    # [3] each cloud's origin for the stages after the anchor stage (its centroid there; zero before), which the
    # sample stage subtracts from the rows it keeps
    src_anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tgt_anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))


def validate(source: ArrayLike, target: ArrayLike, options: RegistrationOptions | None, overrides: dict,
             default_iterations: int, default_keypoints: int) -> Request:
    """Check the clouds first, then the options (``options`` with keyword ``overrides``), then fill in the model's
    ``default_iterations`` / ``default_keypoints``; the first problem raises ``InputError``."""
    src = check_cloud(source, "source")
    tgt = check_cloud(target, "target")
    opts = RegistrationOptions.of(options, **overrides)
    iterations, keypoints = opts.network(default_iterations, default_keypoints)
    hypotheses = search_rotations_for(int(opts.search_rotations)) if opts.search != "off" else None
    R_init, t_init = np.eye(3), np.zeros(3)
    if opts.initial_transform is not None:
        R_init, t_init = check_transform(opts.initial_transform)
    return Request(src, tgt, opts, iterations, keypoints, R_init, t_init, hypotheses)
