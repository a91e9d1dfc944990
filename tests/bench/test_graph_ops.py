"""``python -m bench.graph_ops`` on the bundled model: real graphs, real ONNX Runtime profiles."""

from __future__ import annotations

import numpy as np
import pytest

from bench.graph_ops import main, multiply_adds, run


def test_multiply_adds_of_a_product_is_output_size_times_inner_size():
    assert multiply_adds([[2, 12, 768, 64], [64, 64]], [2, 12, 768, 64]) == 2 * 12 * 768 * 64 * 64
    assert multiply_adds([[16384, 32], [32, 32], [32]], [16384, 32]) == 16384 * 32 * 32


@pytest.fixture(scope="module")
def pairs_file(tmp_path_factory):
    rng = np.random.default_rng(0)
    source = rng.normal(size=(1, 300, 3)).astype(np.float32)
    path = tmp_path_factory.mktemp("ops") / "pairs.npz"
    np.savez(path, source=source, target=source + np.float32(0.05), rotation=np.eye(3)[None],
             translation=np.zeros((1, 3)))
    return path


def test_profiles_every_graph_and_counts_the_encoders_multiply_adds(pairs_file):
    report = run(pairs_file, "clean", repeats=2, threads=1)
    graphs = report["graphs"]
    assert set(graphs) == {"encoder", "matcher_0", "matcher_1", "matcher_2", "matcher_3"}
    batch, n, _ = map(int, report["input_shapes"]["encoder"]["points"].split("x"))
    assert batch == 2 and 280 <= n <= 300  # a few isolated points of the Gaussian blob are left out
    encoder = graphs["encoder"]
    # five blocks: per point W x (3 -> 64, then 64 -> 64 four times) and the point layer; per edge the 64 x 64
    # layer over k = 12 neighbours; both clouds; the significance head (64 -> 64 -> 32 -> 1) per point. Only the
    # first block's 3 -> 64 layer and the head's 32 -> 1 are narrow.
    per_point = 3 * 64 + 4 * 64 * 64 + 5 * 64 * 64 + 5 * 12 * 64 * 64 + 64 * 64 + 64 * 32 + 32
    assert encoder["products_gmac"] == pytest.approx(2 * n * per_point / 1e9, rel=1e-3)
    assert 0 < encoder["wide_products_ms"] < encoder["products_ms"] <= encoder["ms_in_ops"]
    assert encoder["wide_products_gmac"] == pytest.approx(2 * n * (per_point - 3 * 64 - 32) / 1e9, rel=1e-3)
    assert "MatMul" in encoder["ops"] and encoder["ops"]["MatMul"]["nodes"] >= 10
    registration = report["registration"]
    assert registration["iterations"] == 4
    assert 0 < registration["wide_products_ms"] < registration["products_ms"] < registration["graphs_ms"] * 2


def test_cli_writes_the_report(pairs_file, tmp_path, capsys):
    out = tmp_path / "ops.json"
    main(["--pairs", str(pairs_file), "--model", "clean", "--repeats", "1", "--threads", "1", "--json", str(out)])
    assert '"wide_products_ms"' in out.read_text()
    assert '"wide_products_ms"' in capsys.readouterr().out


def test_a_registration_counts_the_encoder_once_per_cloud_where_their_sizes_differ(tmp_path):
    """Clouds of different sizes run the encoder once each: the registration's figures count both calls."""
    rng = np.random.default_rng(1)
    source = rng.normal(size=(1, 300, 3)).astype(np.float32)
    path = tmp_path / "pairs.npz"
    np.savez(path, source=source, target=source[:, :250] + np.float32(0.05), rotation=np.eye(3)[None],
             translation=np.zeros((1, 3)))
    report = run(path, "clean", repeats=2, threads=1)
    registration, graphs = report["registration"], report["graphs"]
    assert report["input_shapes"]["encoder"]["points"].startswith("1x") and registration["encoder_calls"] == 2
    matchers = sum(graphs[f"matcher_{min(i, 3)}"]["products_ms"] for i in range(registration["iterations"]))
    assert registration["products_ms"] == pytest.approx(2 * graphs["encoder"]["products_ms"] + matchers, abs=2e-3)
