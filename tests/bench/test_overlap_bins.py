"""``python -m bench.overlap_bins``: each pair's overlap under its true pose, and each method's recall per bin."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.overlap_bins import main
from model.data import save_pairs

SHARES = (0.3, 0.6, 0.8, 1.0)  # one pair in each default bin


@pytest.fixture()
def pairs_file(tmp_path):
    """Four pairs of 100 points whose target holds the moved copies of the first ``share`` of the source's points,
    the others 10 units away: overlaps of exactly ``SHARES``."""
    rng = np.random.default_rng(0)
    source, target, rotation, translation = [], [], [], []
    for share in SHARES:
        src = rng.uniform(-1, 1, size=(100, 3))  # [N, 3]
        R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
        tgt = src @ R.T + t  # [N, 3]
        tgt[int(share * 100):] += 10.0
        source.append(src), target.append(tgt), rotation.append(R), translation.append(t)
    return save_pairs(tmp_path / "pairs.npz", {"source": np.array(source), "target": np.array(target),
                                               "rotation": np.array(rotation), "translation": np.array(translation)})


def per_pair(path, rotation_error_deg, translation_error):
    np.savez(path, rotation_error_deg=np.array(rotation_error_deg), translation_error=np.array(translation_error))
    return path


def test_each_pair_falls_in_the_bin_of_its_overlap_and_each_method_is_counted_there(pairs_file, tmp_path):
    right = per_pair(tmp_path / "right.npz", [0.5, 0.5, 0.5, 0.5], [0.005, 0.005, 0.005, 0.005])
    mixed = per_pair(tmp_path / "mixed.npz", [0.5, 3.0, 10.0, 0.5], [0.005, 0.02, 0.0, 0.06])
    out = tmp_path / "bins.json"
    report = main([str(pairs_file), f"right={right}", f"mixed={mixed}", "--json", str(out)])
    assert json.loads(out.read_text()) == report
    assert [(b["overlap"], b["pairs"]) for b in report["bins"]] == [
        ("< 0.5", 1), ("0.5-0.7", 1), ("0.7-0.9", 1), (">= 0.9", 1)]
    assert [b["methods"]["right"] for b in report["bins"]] == [{"recall_r1_t001": 1.0, "recall_r5_t005": 1.0}] * 4
    # 5 deg and 0.05: in, in (3 deg, 0.02), out (10 deg), out (0.06); 1 deg and 0.01: only the first
    assert [b["methods"]["mixed"]["recall_r5_t005"] for b in report["bins"]] == [1.0, 1.0, 0.0, 0.0]
    assert [b["methods"]["mixed"]["recall_r1_t001"] for b in report["bins"]] == [1.0, 0.0, 0.0, 0.0]


def test_other_edges_and_an_empty_bin(pairs_file, tmp_path):
    right = per_pair(tmp_path / "right.npz", [0.5] * 4, [0.005] * 4)
    report = main([str(pairs_file), f"right={right}", "--edges", "0.5", "0.55"])
    assert [(b["overlap"], b["pairs"]) for b in report["bins"]] == [("< 0.5", 1), ("0.5-0.55", 0), (">= 0.55", 3)]
    assert report["bins"][1]["methods"]["right"] == {"recall_r1_t001": None, "recall_r5_t005": None}


@pytest.mark.parametrize(("argv", "message"), [
    (["short={short}"], "3 results for 4 pairs"),
    (["short"], "expected NAME=PER_PAIR.npz"),
    (["a={good}", "a={good}"], "'a' is given twice"),
    (["json={pairs}.json"], "no such file"),
    (["pairs={pairs}"], "not a per-pair file of mfgnet evaluate"),
    (["short={short}", "--edges", "0.7", "0.5"], "--edges must increase strictly"),
])
def test_a_mistake_is_a_usage_error(pairs_file, tmp_path, capsys, argv, message):
    short = per_pair(tmp_path / "short.npz", [0.5] * 3, [0.005] * 3)
    good = per_pair(tmp_path / "good.npz", [0.5] * 4, [0.005] * 4)
    with pytest.raises(SystemExit) as stop:
        main([str(pairs_file), *(a.format(short=short, good=good, pairs=pairs_file) for a in argv)])
    assert stop.value.code == 2
    assert message in capsys.readouterr().err
