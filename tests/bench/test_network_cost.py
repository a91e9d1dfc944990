"""``bench.network_cost``: untrained networks of other shapes served as the service serves them, and timed."""

from __future__ import annotations

import json

import pytest

from bench.network_cost import exported, main
from bench.real_scans import data_dir

PAIR = "dragon_48_24"


def test_a_shape_is_exported_as_asked_and_registers(tmp_path):
    registrar = exported({"emb_dims": 16, "encoder_blocks": 2, "iterations": 2}, tmp_path)
    assert (registrar.config["emb_dims"], registrar.config["encoder_blocks"], registrar.config["iterations"]) == (
        16, 2, 2)
    assert len(registrar.matchers) == 2  # one matcher graph per iteration


@pytest.mark.skipif(not (data_dir() / f"{PAIR}.npz").exists(),
                    reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")
@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
def test_the_report_has_one_row_per_shape_the_first_the_reference(tmp_path):
    out = tmp_path / "cost.json"
    report = main(["--pair", PAIR, "--rounds", "2", "--shapes", "{}", '{"iterations": 2}', "--json", str(out)])
    first, second = report["rows"]
    assert first["shape"] == {} and first["of_first"] == 1.0 and second["shape"] == {"iterations": 2}
    assert first["network_ms"] > 0 and second["network_ms"] > 0
    assert json.loads(out.read_text())["rows"] == report["rows"]
