"""``python -m bench.select``: checkpoints compared through the service's pipeline on the same pairs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from pair_checks import needs_modelnet

from bench.runtime_eval import runtime_poses
from bench.select import main, select
from model.checkpoint import read_checkpoint, resolve_checkpoint
from model.data import make_test_pairs, save_pairs
from model.metrics import registration_metrics


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
@needs_modelnet
def test_the_bundled_checkpoint_scores_as_the_served_model_and_a_damaged_one_worse(tmp_path) -> None:
    pairs = make_test_pairs("resampled", "test", count=6, seed=3)
    pairs_file = tmp_path / "pairs.npz"
    save_pairs(pairs_file, pairs)
    damaged = read_checkpoint(resolve_checkpoint("general"))
    generator = torch.Generator().manual_seed(0)
    damaged["model"] = {k: v + 0.5 * v.std() * torch.randn(v.shape, generator=generator)
                        if v.is_floating_point() and v.numel() > 1 else v for k, v in damaged["model"].items()}
    torch.save(damaged, tmp_path / "damaged.pt")

    rows = select(["general", str(tmp_path / "damaged.pt")], [pairs_file], "none")
    assert [r["checkpoint"] for r in rows] == ["general", str(tmp_path / "damaged.pt")]

    R, t, *_ = runtime_poses("general", pairs, progress=False)  # the bundled ONNX model as served
    served = registration_metrics(R, t, pairs["rotation"], pairs["translation"])
    assert rows[0]["iso_r_median"] == pytest.approx(served["iso_r_median"], abs=1e-3)
    assert rows[0]["recall_r5_t005"] == served["recall_r5_t005"]
    assert rows[1]["iso_r_median"] > rows[0]["iso_r_median"] + 1.0  # the damage shows


@needs_modelnet
def test_the_command_writes_one_row_per_checkpoint_and_pairs_file(tmp_path, capsys) -> None:
    files = []
    for seed in (1, 2):
        files.append(tmp_path / f"pairs_{seed}.npz")
        save_pairs(files[-1], make_test_pairs("resampled", "test", count=2, seed=seed))
    out = tmp_path / "rows.json"
    main(["--checkpoint", "general", "--pairs", str(files[0]), "--pairs", str(files[1]), "--refine", "icp-plane",
          "--json", str(out)])
    rows = json.loads(out.read_text())
    assert [(r["pairs"], r["refine"]) for r in rows] == [(str(f), "icp-plane") for f in files]
    assert all(np.isfinite(r["mae_r"]) and 0 <= r["reliable_wrong_share"] <= 1 for r in rows)
    assert "pairs_2.npz" in capsys.readouterr().out


def test_an_unknown_refinement_is_refused_before_any_work(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["--checkpoint", "general", "--pairs", "missing.npz", "--refine", "icp-fancy"])
    assert "unknown --refine 'icp-fancy'" in capsys.readouterr().err
