"""``bench.auto_trigger report`` replays search triggers on collected per-pair results."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.auto_trigger import report, switches
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


def test_switches_follows_the_registrars_ranking_and_a_margin_holds_the_plain_pose() -> None:
    row = {"ratio": 0.60, "rms": 0.02, "searched_ratio": 0.64, "searched_rms": 0.03}
    assert switches(row, 0.0) and not switches(row, 0.05)  # higher ratio wins, unless by less than the margin
    assert switches({**row, "searched_ratio": 0.60, "searched_rms": 0.01}, 0.0)  # a tie goes to the lower residual
    assert not switches({**row, "searched_ratio": 0.60, "searched_rms": 0.02}, 0.0)  # a full tie keeps the plain pose


def test_replay_of_switch_margins_counts_the_poses_they_keep_and_lose(tmp_path) -> None:
    k = np.arange(4000) + 0.5
    z, phi = 1 - 2 * k / 4000, np.pi * (1 + 5**0.5) * k
    sphere = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], axis=1)
    path = tmp_path / "two.npz"
    np.savez(path, source=np.stack([sphere] * 2), target=np.stack([sphere] * 2))
    right, wrong = (0.5, 0.01), (170.0, 0.02)
    common = {"reliable": True, "ms_plain": 10, "ms_both": 100, "rms": 0.02, "searched_rms": 0.02}
    rows = [  # both searched (0.5 < 0.8 x attainable): a right pose flipped by a small gain, a wrong one fixed
        {**common, "ratio": 0.50, "plain": right, "searched": wrong, "searched_ratio": 0.53, "auto_always": wrong},
        {**common, "ratio": 0.30, "plain": wrong, "searched": right, "searched_ratio": 0.70, "auto_always": right},
    ]
    table = report({"two": rows}, [path], "general")["two"]
    none = table["relative 0.8, switch margin 0.0"]
    assert none == {"recall_r5_t005": 0.5, "switched": 1.0, "right_to_wrong": 1, "wrong_to_right": 1}
    held = table["relative 0.8, switch margin 0.05"]
    assert held == {"recall_r5_t005": 1.0, "switched": 0.5, "right_to_wrong": 0, "wrong_to_right": 1}
    assert "relative 0.8, switch margin 0.0" not in report({"two": [
        {key: value for key, value in row.items() if not key.startswith("searched")} for row in rows]},
        [path], "general")["two"]  # files collected before the searched pose was recorded: triggers only


COLLECTED = {"ratio": 0.9, "rms": 0.01, "reliable": True, "plain": [0.5, 0.01], "ms_plain": 10.0,
             "searched": [0.4, 0.01], "searched_ratio": 0.9, "searched_rms": 0.01, "auto_always": [0.5, 0.01],
             "ms_both": 100.0}  # one row as collect writes it


@pytest.mark.parametrize(("rows", "fragment"), [
    ([{k: v for k, v in COLLECTED.items() if k != "ms_both"}, COLLECTED], "two row 0: no field 'ms_both'"),
    ([COLLECTED, {k: v for k, v in COLLECTED.items() if k != "ratio"}], "two row 1: no field 'ratio'"),
    ([{k: v for k, v in COLLECTED.items() if k != "searched_rms"}] * 2, "two row 0: no field 'searched_rms'"),
    ([COLLECTED, {**COLLECTED, "plain": 3.0}], "two row 1: field 'plain' is 3.0, not [rotation deg, translation]"),
    ([{**COLLECTED, "reliable": "yes"}] * 2, "two row 0: field 'reliable' is \"yes\", not true or false"),
    ([COLLECTED, [1, 2]], "two row 1: not an object of fields"),
    ([COLLECTED], "two has 1 rows, but its pairs file holds 2 pairs"),
], ids=["missing", "second row", "searched group", "errors type", "bool type", "not an object", "count"])
def test_report_of_bad_rows_is_a_usage_error_naming_file_row_and_field(rows, fragment, tmp_path, capsys) -> None:
    from bench.auto_trigger import main

    rng = np.random.default_rng(0)
    pairs = tmp_path / "two.npz"
    np.savez(pairs, source=rng.normal(size=(2, 8, 3)), target=rng.normal(size=(2, 8, 3)),
             rotation=np.stack([np.eye(3)] * 2), translation=np.zeros((2, 3)), label=np.zeros(2))
    results = tmp_path / "trigger.json"
    results.write_text(json.dumps({"two": rows}))
    with pytest.raises(SystemExit) as ended:
        main(["report", str(results), "--pairs", str(pairs)])
    assert ended.value.code == 2
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"error: results {results}: " in message
    assert fragment in message and f"--pairs {pairs}" in message


def test_report_command_of_a_row_lacking_a_field_ends_without_a_traceback(tmp_path) -> None:
    import subprocess
    import sys

    rng = np.random.default_rng(0)
    pairs = tmp_path / "one.npz"
    np.savez(pairs, source=rng.normal(size=(1, 8, 3)), target=rng.normal(size=(1, 8, 3)),
             rotation=np.eye(3)[None], translation=np.zeros((1, 3)), label=np.zeros(1))
    results = tmp_path / "trigger.json"
    results.write_text(json.dumps({"one": [{k: v for k, v in COLLECTED.items() if k != "auto_always"}]}))
    done = subprocess.run([sys.executable, "-m", "bench.auto_trigger", "report", str(results), "--pairs", str(pairs)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr and done.stdout == ""
    assert "one row 0: no field 'auto_always'" in done.stderr
