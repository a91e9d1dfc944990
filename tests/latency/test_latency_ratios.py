"""Latency regression guard: stage time / reference workload must not grow past the baseline by more
than ``MARGIN``. Run alone with ``pytest -m latency``; refresh with ``latency_stages.py --write``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from latency_stages import measure  # tests/helpers (on sys.path through pyproject pythonpath)

from service.manifest import bundled_models_dir

BASELINE = Path(__file__).with_name("baseline.json")
MARGIN = 2.0  # fail past 2x the baseline: two quiet runs on the 2-vCPU VM differed by up to 1.5x

pytestmark = [
    pytest.mark.latency,
    pytest.mark.serial,  # timing ratios: `make test` runs them alone, after the parallel part
    pytest.mark.skipif(not (bundled_models_dir() / "clean" / "manifest.json").exists(), reason="no bundled model"),
    pytest.mark.skipif(not BASELINE.exists(), reason="no committed latency baseline"),
]


@pytest.fixture(scope="module")
def ratios() -> dict[str, float]:
    return measure(include_http=True)


@pytest.mark.parametrize(
    "stage", ["encoder", "one_iteration", "svd", "preprocessing", "register_in_process", "register_http"]
)
def test_stage_latency_ratio_has_not_regressed(ratios, stage):
    baseline = json.loads(BASELINE.read_text())[stage]
    assert ratios[stage] <= MARGIN * baseline, (
        f"stage '{stage}' regressed: {ratios[stage]:.3f} x reference vs baseline {baseline:.3f} "
        f"(limit {MARGIN}x; reference workload took {ratios['reference_ms']:.2f} ms here)"
    )
