"""``python -m bench.pair_batches``: ms per training batch of a recipe's pairs, per share of camera-view batches."""

from __future__ import annotations

import json

import pytest

from bench.pair_batches import main
from model.data import data_dir


@pytest.mark.skipif(not data_dir().is_dir(), reason="ModelNet40 absent (set MFGNET_DATA)")
def test_each_share_gets_its_time(tmp_path) -> None:
    out = tmp_path / "batches.json"
    main(["--views-share", "0", "--views-share", "1", "--batch-size", "2", "--batches", "1", "--json", str(out)])
    report = json.loads(out.read_text())
    assert set(report["ms_per_batch"]) == {"0.0", "1.0"} and all(ms > 0 for ms in report["ms_per_batch"].values())


def test_a_share_outside_0_to_1_is_a_usage_error(capsys) -> None:
    with pytest.raises(SystemExit) as ended:
        main(["--views-share", "2"])
    assert ended.value.code == 2 and "a share of batches, 0-1" in capsys.readouterr().err
