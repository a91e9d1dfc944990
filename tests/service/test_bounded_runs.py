"""ONNX Runtime calls split along the batch to a budget, on one shared arena: the same outputs, bounded memory."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from shapes import bumpy_ellipsoid

from service.bounded_runs import MATCH_PAIRS_PER_CALL, run_bounded
from service.manifest import bundled_models_dir
from service.registrar import Registrar, embedding_distance

BUNDLED = bundled_models_dir() / "general"
pytestmark = pytest.mark.skipif(not (BUNDLED / "manifest.json").exists(), reason="bundled model 'general' absent")


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return Registrar(BUNDLED, threads=1, warmup=False)


def matcher_feeds(registrar: Registrar, batch: int, keypoints: int) -> dict[str, np.ndarray]:
    """Inputs of a matcher call of ``batch`` rows of ``keypoints`` x ``keypoints`` pairs from encoded clouds."""
    clouds = np.stack([bumpy_ellipsoid(keypoints, seed) for seed in range(batch)]).astype(np.float32)  # [B, K, 3]
    emb, _ = registrar.embed(clouds)  # [B, K, D]
    feeds = {"src_xyz": clouds, "tgt_xyz": clouds[::-1].copy(), "src_emb": emb, "tgt_emb": emb[::-1].copy()}
    if registrar.matcher_takes_distance:
        feeds["emb_dist"] = embedding_distance(feeds["src_emb"], feeds["tgt_emb"])
    return feeds


@pytest.mark.parametrize("budget", [3 * 64 * 64, 2 * 64 * 64, 64 * 64, 100])
def test_a_call_split_to_any_budget_gives_the_outputs_of_one_call(registrar, budget):
    feeds = matcher_feeds(registrar, 3, 64)
    whole = registrar.matchers[0].run(None, feeds)
    split = run_bounded(registrar.matchers[0], feeds, 64 * 64, budget)
    assert [a.shape for a in split] == [a.shape for a in whole]
    for a, b in zip(split, whole, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


def test_the_defaults_largest_matcher_call_is_not_split():
    assert 4 * 128 * 128 <= MATCH_PAIRS_PER_CALL < 2 * 4 * 128 * 128


# The rotation search of refine "none" at the options' limits: four hypotheses of 512 x 512 keypoint pairs per call
# on two matcher sessions; each session kept ~700 MB when the calls ran whole on their own arenas.
LIMITS_SCRIPT = """
import resource, sys
import numpy as np
sys.path.insert(0, sys.argv[2])
from shapes import bumpy_ellipsoid
from service.registrar import Registrar
registrar = Registrar(sys.argv[1], threads=1)
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
result = registrar.register(bumpy_ellipsoid(768, 0), bumpy_ellipsoid(768, 1), refine="none", rotation_search=True,
                            keypoints=512, iterations=2)
assert np.isfinite(result.rotation).all()
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) // 1024)
"""


def test_a_search_at_the_option_limits_stays_within_a_bounded_memory():
    helpers = str(Path(__file__).resolve().parents[1] / "helpers")  # where `shapes` lives
    done = subprocess.run([sys.executable, "-c", LIMITS_SCRIPT, str(BUNDLED), helpers], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    grown_mib = int(done.stdout.split()[-1])
    print(f"peak grew by {grown_mib} MiB")
    assert grown_mib < 600
