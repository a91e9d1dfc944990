"""The classical baselines' timing harness: one-off set-up is not charged to the timed pairs."""

from __future__ import annotations

import time

import numpy as np

from bench.baselines import run_method


def test_run_method_runs_once_untimed_before_timing_the_pairs() -> None:
    calls = []

    def slow_first_call(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not calls:
            time.sleep(0.5)  # stands in for Open3D's import on the first call
        calls.append(len(src))
        return np.eye(3), tgt.mean(0) - src.mean(0)

    rng = np.random.default_rng(0)
    pairs = {"source": rng.normal(size=(3, 16, 3)), "target": rng.normal(size=(3, 16, 3))}
    R, t, seconds = run_method(slow_first_call, pairs)
    assert len(calls) == 4  # the untimed warm-up, then every pair
    assert seconds < 0.25
    assert R.shape == (3, 3, 3) and t.shape == (3, 3)
    assert np.allclose(t, pairs["target"].mean(1) - pairs["source"].mean(1))
