"""``export.auto_trigger report`` replays search triggers on collected per-pair results."""

from __future__ import annotations

import numpy as np
import pytest

from export.auto_trigger import report
from service.manifest import bundled_models_dir

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")


def test_replay_searches_the_flagged_pairs_and_takes_their_searched_result(tmp_path) -> None:
    k = np.arange(4000) + 0.5  # a Fibonacci sphere: dense enough that nearly every point has a close neighbour
    z, phi = 1 - 2 * k / 4000, np.pi * (1 + 5**0.5) * k
    sphere = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], axis=1)
    path = tmp_path / "three.npz"
    np.savez(path, source=np.stack([sphere] * 3), target=np.stack([sphere] * 3))
    right, wrong = (0.5, 0.01), (40.0, 0.2)
    rows = [  # plain ratio / reliability, plain and searched errors, times
        {"ratio": 0.95, "reliable": True, "plain": right, "auto_always": right, "ms_plain": 10, "ms_both": 100},
        {"ratio": 0.72, "reliable": True, "plain": wrong, "auto_always": right, "ms_plain": 10, "ms_both": 100},
        {"ratio": 0.5, "reliable": False, "plain": wrong, "auto_always": wrong, "ms_plain": 10, "ms_both": 100},
    ]
    table = report({"three": rows}, [path], "general")["three"]
    assert table["pairs"] == 3 and table["plain"] == pytest.approx(1 / 3) and table["always"] == pytest.approx(2 / 3)
    assert table["attainable_median"] > 0.95
    fixed = table["fixed 0.7 or unreliable"]  # searches only the unreliable pair
    assert fixed["searched"] == pytest.approx(1 / 3) and fixed["recall_r5_t005"] == pytest.approx(1 / 3)
    assert fixed["ms_per_pair"] == pytest.approx(40)
    relative = table["relative 0.8"]  # 0.72 and 0.5 < 0.8 x attainable: the second pair is searched and fixed
    assert relative["searched"] == pytest.approx(2 / 3) and relative["recall_r5_t005"] == pytest.approx(2 / 3)
    assert table["relative 0.8 or unreliable"] == relative  # the unreliable pair is below the ratio anyway
    assert table["relative 0.7"]["searched"] == pytest.approx(1 / 3)  # 0.72 >= 0.7 x attainable: not searched
