"""Poses of a pairs file through the service's own pipeline (``Registrar.register``), for evaluation."""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np


class RuntimeRun(NamedTuple):
    """What :func:`runtime_poses` measured over ``M`` pairs."""

    rotation: np.ndarray  # [M, 3, 3] src_to_tgt
    translation: np.ndarray  # [M, 3]
    seconds: float  # wall time of all registrations
    searched: int  # pairs on which the rotation search ran (``timing_ms["search"]``)
    reliable: np.ndarray  # [M] bool: ``quality.reliable``
    stability: np.ndarray  # [M] float: ``quality.stability`` (NaN where the runtime gives none)
    warnings: list[tuple[str, ...]]  # [M] per pair its warnings' kinds (each the text before its colon), sorted
    inlier_ratio: np.ndarray  # [M] float: ``quality.inlier_ratio``


def runtime_poses(model: str | Path, pairs: dict, iterations: int | None = None, keypoints: int | None = None,
                  refine: str = "none", rotation_search: bool | str = False, refine_points: int | None = None,
                  progress: bool = True) -> RuntimeRun:
    """Every pair of ``pairs`` registered by the bundled model (or model folder) ``model``, in order."""
    from tqdm import tqdm

    from service.manifest import model_folder
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    Rs, ts, searched, reliable, stability, warnings, ratios = [], [], 0, [], [], [], []
    begin = time.perf_counter()
    pairs_in_order = list(zip(pairs["source"], pairs["target"], strict=True))
    for src, tgt in tqdm(pairs_in_order, desc="evaluate", unit="pair", disable=not progress):
        res = registrar.register(src, tgt, iterations=iterations, keypoints=keypoints, refine=refine,
                                 rotation_search=rotation_search, refine_points=refine_points)
        Rs.append(res.rotation)
        ts.append(res.translation)
        searched += "search" in res.timing_ms
        reliable.append(res.reliable)
        stability.append(np.nan if res.stability is None else res.stability)
        warnings.append(tuple(sorted({warning.split(":", 1)[0] for warning in res.warnings})))
        ratios.append(res.inlier_ratio)
    return RuntimeRun(np.stack(Rs), np.stack(ts), time.perf_counter() - begin, searched,
                      np.array(reliable, dtype=bool), np.array(stability, dtype=np.float64), warnings,
                      np.array(ratios, dtype=np.float64))
