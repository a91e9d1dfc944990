"""Poses of a pairs file through the service's own pipeline (``Registrar.register``), for evaluation."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np


def runtime_poses(model: str | Path, pairs: dict, iterations: int | None = None, keypoints: int | None = None,
                  refine: str = "none", rotation_search: bool | str = False, refine_points: int | None = None,
                  progress: bool = True):
    """Poses ``R [M, 3, 3]``, ``t [M, 3]`` of every pair registered by the bundled model (or model folder)
    ``model``, the seconds they took, on how many pairs the rotation search ran (``timing_ms["search"]``) and
    each result's ``reliable`` flag ``[M]``."""
    from tqdm import tqdm

    from service.manifest import model_folder
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    Rs, ts, searched, reliable = [], [], 0, []
    begin = time.perf_counter()
    pairs_in_order = list(zip(pairs["source"], pairs["target"], strict=True))
    for src, tgt in tqdm(pairs_in_order, desc="evaluate", unit="pair", disable=not progress):
        res = registrar.register(src, tgt, iterations=iterations, keypoints=keypoints, refine=refine,
                                 rotation_search=rotation_search, refine_points=refine_points)
        Rs.append(res.rotation)
        ts.append(res.translation)
        searched += "search" in res.timing_ms
        reliable.append(res.reliable)
    return np.stack(Rs), np.stack(ts), time.perf_counter() - begin, searched, np.array(reliable, dtype=bool)
