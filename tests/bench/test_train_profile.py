"""``python -m bench.train_profile``: training steps timed on fixed batches, and with ``--profile`` the torch
profiler's op shares stored (BENCHMARKS' "A CPU training step")."""

from __future__ import annotations

import json

import pytest

from bench.train_profile import main, product_dims
from model.data import data_dir


def test_product_dims_read_each_products_factors() -> None:
    assert product_dims("aten::mm", [[16384, 32], [32, 32]]) == (1, 16384, 32, 32)
    assert product_dims("aten::addmm", [[64], [12288, 64], [64, 64], [], []]) == (1, 12288, 64, 64)
    assert product_dims("aten::addmm_", [[32, 32], [32, 16384], [16384, 32], [], []]) == (1, 32, 16384, 32)
    assert product_dims("aten::bmm", [[2, 128, 128], [2, 128, 32]]) == (2, 128, 128, 32)
    assert product_dims("aten::mul", [[3, 3], [3, 3]]) is None
    assert product_dims("aten::mm", [[4, 5], [6, 7]]) is None  # not a product's shapes: not counted
    assert product_dims("aten::addmm", [[64], [12288, 64]]) is None


@pytest.mark.skipif(not data_dir().is_dir(), reason="ModelNet40 absent (set MFGNET_DATA)")
def test_profile_stores_the_steps_ops_and_the_products_share_by_width(tmp_path) -> None:
    out = tmp_path / "profile.json"
    main(["--steps", "1", "--batch-size", "2", "--profile", "--json", str(out)])
    report = json.loads(out.read_text())
    assert len(report["ms_per_training_pair"]["fused"]["steps"]) == 1
    profile = report["profile"]
    shares = profile["products_by_width"]
    # the matchers' hidden layers are 32 wide, the encoder's 64: both products and their gradients
    assert shares["32"]["share"] > 0.05 and shares["64"]["share"] > 0.05
    assert sum(share["share"] for share in shares.values()) < 1
    assert len(profile["ops"]) == 30 and profile["ops"][0]["self_cpu_ms"] >= profile["ops"][-1]["self_cpu_ms"]
    assert any(op["op"] == "aten::mm" for op in profile["ops"])
    shares_ms = sum(op["share"] for op in profile["ops"]) * profile["self_cpu_ms"]  # each share rounded to 1e-4
    assert abs(shares_ms - sum(op["self_cpu_ms"] for op in profile["ops"])) < 30 * 5e-5 * profile["self_cpu_ms"] + 0.1
