"""Training: a few optimizer steps lower the loss, ``model.train.train`` writes and resumes its run
directory, and checkpoints reproduce the network exactly."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from shapes import sphere_shapes
from tiny_training import sigterm_in_step

from model.checkpoint import load_model, read_checkpoint, resolve_checkpoint, save_checkpoint
from model.config import MFGNetConfig
from model.data import PairProtocol, TrainPairStream, make_pairs
from model.losses import registration_losses, sample_training_keypoints
from model.network import MFGNet
from model.recipes import recipe_draw
from model.train import RUN_FILES, TrainOptions, epoch_batches, lr_at, run_training, train

TINY = {"iterations": 2, "keypoints": 32, "emb_dims": 16, "encoder_blocks": 2, "matcher_channels": 8,
        "knn": 8, "train_positives": 16, "train_negatives": 16}


def training_batch(seed: int = 0) -> tuple[torch.Tensor, ...]:
    pairs = make_pairs(sphere_shapes(2, seed=seed), PairProtocol(), np.random.default_rng(seed))
    return tuple(torch.from_numpy(pairs[k]) for k in ("source", "target", "rotation", "translation"))


def test_five_adam_steps_on_a_fixed_batch_lower_the_total_loss() -> None:
    torch.manual_seed(0)
    cfg = MFGNetConfig(**TINY)
    model = MFGNet(cfg).train()
    src, tgt, R, t = training_batch()
    src_idx, tgt_idx = sample_training_keypoints(src, tgt, R, t, cfg.train_positives, cfg.train_negatives,
                                                 cfg.match_threshold, torch.Generator().manual_seed(0))
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def total_loss() -> torch.Tensor:
        out = model(src, tgt, src_idx=src_idx, tgt_idx=tgt_idx)
        return registration_losses(out, src, tgt, R, t, cfg.match_threshold).total

    losses = []
    for _ in range(5):
        loss = total_loss()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    final = float(total_loss().detach())
    assert all(np.isfinite(losses))
    assert final < 0.95 * losses[0], (losses, final)


def test_every_parameter_receives_a_gradient() -> None:
    torch.manual_seed(0)
    cfg = MFGNetConfig(**TINY)
    model = MFGNet(cfg).train()
    src, tgt, R, t = training_batch(1)
    src_idx, tgt_idx = sample_training_keypoints(src, tgt, R, t, 16, 16, cfg.match_threshold)
    out = model(src, tgt, src_idx=src_idx, tgt_idx=tgt_idx)
    registration_losses(out, src, tgt, R, t, cfg.match_threshold).total.backward()
    no_grad = [name for name, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert no_grad == []


# --- the training loop ----------------------------------------------------------------------------


@pytest.fixture
def synthetic_modelnet(tmp_path):
    """A ModelNet40-shaped training file of 40 sphere shapes (float16 like the real one)."""
    folder = tmp_path / "data"
    folder.mkdir()
    np.savez(folder / "modelnet40_train.npz", points=sphere_shapes(40, seed=3).astype(np.float16),
             labels=np.arange(40) % 20)
    return folder


def options(out, data, **overrides) -> TrainOptions:
    return TrainOptions(**{
        "out": str(out), "data": str(data), "epochs": 1, "batch_size": 2, "max_batches_per_epoch": 2,
        "val_pairs": 8, "device": "cpu", "config": dict(TINY), **overrides})


def test_train_writes_checkpoints_and_log_and_resume_continues(tmp_path, synthetic_modelnet, capsys) -> None:
    run = tmp_path / "run"
    best = train(options(run, synthetic_modelnet))
    assert best == run / "best.pt"
    assert {"best.pt", "last.pt", "log.jsonl", "config.json"} <= {p.name for p in run.iterdir()}
    assert not list(run.glob("*.tmp"))
    assert not (run / "snapshots").exists()  # only with snapshot_every
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in records] == [0]
    assert records[0]["batches"] == 2
    assert records[0]["lr"] == 1e-4  # a one-epoch run trains at its lr, not at the dropped one
    expected_keys = {"train_total", "train_keypoint", "train_matching", "train_credibility",
                     "val_mae_r", "val_n"}
    assert expected_keys <= set(records[0])
    assert np.isfinite(records[0]["train_total"])
    last = read_checkpoint(run / "last.pt")
    assert last["state"]["epoch"] == 1
    assert last["config"]["emb_dims"] == TINY["emb_dims"]
    assert "optimizer" in last
    first_weights = {k: v.clone() for k, v in last["model"].items()}
    assert load_model(run / "best.pt").cfg == MFGNetConfig(**TINY)

    capsys.readouterr()
    train(options(run, synthetic_modelnet, epochs=2, resume=True))
    assert "resumed from" in capsys.readouterr().out
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in records] == [0, 1]  # the finished epoch is not repeated
    last = read_checkpoint(run / "last.pt")
    assert last["state"]["epoch"] == 2
    changed = [k for k, v in last["model"].items()
               if v.is_floating_point() and not torch.equal(v, first_weights[k])]
    assert changed  # training went on from the saved weights


TIMING_KEYS = {"s_per_pair", "epoch_minutes", "time", "val_ms_per_pair"}  # how fast, not what was trained


def test_a_run_stopped_inside_an_epoch_and_resumed_ends_as_the_uninterrupted_run(
    tmp_path, synthetic_modelnet, monkeypatch
) -> None:
    run_options = {"epochs": 2, "max_batches_per_epoch": 3, "seed": 5}
    whole, run = tmp_path / "whole", tmp_path / "run"
    assert run_training(options(whole, synthetic_modelnet, **run_options)).stopped_by is None

    sigterm_in_step(monkeypatch, 5)  # epoch 1, its second batch
    stopped = run_training(options(run, synthetic_modelnet, **run_options))
    assert stopped.stopped_by == "SIGTERM"
    state = read_checkpoint(run / "last.pt")["state"]
    assert (state["epoch"], state["batch"]) == (1, 2)
    monkeypatch.undo()
    assert run_training(options(run, synthetic_modelnet, resume=True, **run_options)).stopped_by is None

    expected, weights = read_checkpoint(whole / "last.pt"), read_checkpoint(run / "last.pt")
    assert expected["model"].keys() == weights["model"].keys()
    for key, value in expected["model"].items():
        assert torch.equal(value, weights["model"][key]), key  # bitwise: every draw depends on (seed, epoch, batch)
    assert weights["state"] == expected["state"]

    def records(folder):
        lines = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
        assert all(set(r) >= TIMING_KEYS for r in lines)
        return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in lines]

    assert records(run) == records(whole)  # the resumed epoch's record covers its batches before the stop too
    assert records(run)[1]["batches"] == 3


def test_resume_starts_a_new_run_where_there_is_none_and_refuses_other_run_options(
    tmp_path, synthetic_modelnet, capsys
) -> None:
    run = tmp_path / "run"
    train(options(run, synthetic_modelnet, max_batches_per_epoch=1, resume=True))
    assert f"no {run / 'last.pt'} to resume from: starting a new run" in capsys.readouterr().out
    with pytest.raises(ValueError, match="seed, lr, config differ from the run's"):
        train(options(run, synthetic_modelnet, max_batches_per_epoch=1, resume=True, epochs=2, seed=1, lr=1e-3,
                      config={**TINY, "iterations": 3}))
    train(options(run, synthetic_modelnet, max_batches_per_epoch=1, resume=True, epochs=2, patience=3))  # may grow
    assert [json.loads(line)["epoch"] for line in (run / "log.jsonl").read_text().splitlines()] == [0, 1]


@pytest.mark.parametrize("left", RUN_FILES)
def test_train_refuses_a_folder_that_holds_a_run_and_leaves_it_as_it_was(tmp_path, synthetic_modelnet, left) -> None:
    run = tmp_path / "run"
    run.mkdir()
    if left == "snapshots":
        (run / left).mkdir()
    else:
        (run / left).write_bytes(b"the earlier run's")
    before = sorted(p.name for p in run.iterdir())
    with pytest.raises(FileExistsError, match=f"holds a run already \\({left}\\); pass resume"):
        train(options(run, synthetic_modelnet, max_batches_per_epoch=1))
    if left != "last.pt":  # resume needs a last.pt to continue from
        with pytest.raises(FileExistsError, match=f"holds a run \\({left}\\) but no last.pt to resume it from"):
            train(options(run, synthetic_modelnet, max_batches_per_epoch=1, resume=True))
    with pytest.raises(ValueError, match="resume and overwrite exclude each other"):
        train(options(run, synthetic_modelnet, max_batches_per_epoch=1, resume=True, overwrite=True))
    assert sorted(p.name for p in run.iterdir()) == before  # no config.json written, nothing replaced
    if left != "snapshots":
        assert (run / left).read_bytes() == b"the earlier run's"


def test_overwrite_replaces_the_run_in_a_folder_leaving_none_of_its_files(
    tmp_path, synthetic_modelnet, capsys
) -> None:
    run = tmp_path / "run"
    train(options(run, synthetic_modelnet, epochs=2, max_batches_per_epoch=1, snapshot_every=1))
    assert [json.loads(line)["epoch"] for line in (run / "log.jsonl").read_text().splitlines()] == [0, 1]
    with pytest.raises(FileExistsError, match="holds a run already"):  # what overwrote it before, without asking
        train(options(run, synthetic_modelnet, max_batches_per_epoch=1, seed=1))
    assert read_checkpoint(run / "last.pt")["state"]["epoch"] == 2  # the run is kept

    capsys.readouterr()
    assert train(options(run, synthetic_modelnet, max_batches_per_epoch=1, seed=1, overwrite=True)) == run / "best.pt"
    assert "replacing the run in" in capsys.readouterr().out
    assert [json.loads(line)["epoch"] for line in (run / "log.jsonl").read_text().splitlines()] == [0]  # not appended
    assert not (run / "snapshots").exists()  # the replaced run's snapshots are not taken for this one's
    assert read_checkpoint(run / "last.pt")["state"]["epoch"] == 1
    assert json.loads((run / "config.json").read_text())["train"]["seed"] == 1


def test_the_lr_drop_never_falls_on_the_first_epoch() -> None:
    def schedule(epochs: int, drop_at: float = 0.8) -> list[float]:
        opts = TrainOptions(lr=1.0, epochs=epochs, lr_drop_at=drop_at)
        return [lr_at(opts, epoch) for epoch in range(epochs)]

    assert schedule(1) == [1.0]  # was [0.1]: the whole run at a tenth of its lr
    assert schedule(1, drop_at=0.0) == [1.0]
    assert schedule(2) == [1.0, 0.1]
    assert schedule(5) == [1.0, 1.0, 1.0, 1.0, 0.1]
    assert schedule(50) == [1.0] * 40 + [0.1] * 10
    assert schedule(5, drop_at=1.0) == [1.0] * 5  # never


def assert_same_batches(here: list[dict], there: list[dict]) -> None:
    assert len(here) == len(there)
    for a, b in zip(here, there, strict=True):
        assert set(a) == set(b)
        for key in a:
            assert np.array_equal(a[key], np.asarray(b[key])), key


def test_prefetched_batches_are_the_stream_batches_in_order() -> None:
    stream = TrainPairStream(sphere_shapes(15, seed=4), recipe_draw("general"), seed=5)
    here = list(epoch_batches(stream, 1, 3, prefetch=False))
    assert len(here) == 5
    assert_same_batches(here, list(epoch_batches(stream, 1, 3, prefetch=True)))  # made in a worker process
    assert_same_batches(here, list(epoch_batches(stream, 1, 3, prefetch=True, workers=3)))  # 3 workers in turn
    for first in (1, 4):  # a resumed epoch starts at its batch, here or in 2 workers
        assert_same_batches(here[first:], list(epoch_batches(stream, 1, 3, prefetch=False, first=first)))
        assert_same_batches(here[first:], list(epoch_batches(stream, 1, 3, prefetch=True, first=first, workers=2)))
    assert not np.array_equal(here[0]["source"], next(iter(epoch_batches(stream, 2, 3, prefetch=False)))["source"])


def test_prefetched_training_logs_the_same_losses(tmp_path, synthetic_modelnet) -> None:
    logs = []
    for prefetch, workers in ((False, 1), (True, 1), (True, 2)):
        run = tmp_path / f"run_{prefetch}_{workers}"
        train(options(run, synthetic_modelnet, prefetch=prefetch, workers=workers))
        logs.append(json.loads((run / "log.jsonl").read_text())["train_total"])
    assert logs[0] == logs[1] == logs[2]


def test_snapshots_keep_the_weights_of_every_nth_epoch(tmp_path, synthetic_modelnet) -> None:
    run = tmp_path / "run"
    train(options(run, synthetic_modelnet, epochs=3, max_batches_per_epoch=1, snapshot_every=2))
    assert sorted(p.name for p in (run / "snapshots").iterdir()) == ["epoch_0000.pt", "epoch_0002.pt"]
    snapshot = read_checkpoint(run / "snapshots" / "epoch_0002.pt")
    last = read_checkpoint(run / "last.pt")
    assert "optimizer" not in snapshot  # weights to choose from, not a run to resume
    assert all(torch.equal(v, last["model"][k]) for k, v in snapshot["model"].items())  # the last epoch's weights
    assert np.isfinite(snapshot["val"]["mae_r"])
    first = read_checkpoint(run / "snapshots" / "epoch_0000.pt")
    assert any(not torch.equal(v, first["model"][k]) for k, v in snapshot["model"].items() if v.is_floating_point())


def test_train_config_overrides_reach_the_saved_model(tmp_path, synthetic_modelnet) -> None:
    run = tmp_path / "run"
    train(options(run, synthetic_modelnet, config={**TINY, "share_weights": True}, max_batches_per_epoch=1))
    model = load_model(run / "last.pt")
    assert model.cfg.share_weights
    assert len(model.matchers) == 1
    saved = json.loads((run / "config.json").read_text())
    assert saved["model"]["share_weights"] is True
    assert saved["train"]["batch_size"] == 2


# --- checkpoints ----------------------------------------------------------------------------------


def test_checkpoint_round_trip_reproduces_outputs_exactly(tmp_path) -> None:
    torch.manual_seed(0)
    cfg = MFGNetConfig(**{**TINY, "share_weights": True, "feature_diff": "target_minus_source",
                          "centroid": "unweighted"})
    model = MFGNet(cfg)
    src, tgt, _, _ = training_batch(2)
    model.train()
    model(src, tgt)  # move the BatchNorm running statistics away from their defaults
    model.eval()
    save_checkpoint(tmp_path / "ck" / "model.pt", model, note="hello", state={"epoch": 3})
    loaded = load_model(tmp_path / "ck" / "model.pt")
    assert not loaded.training
    assert loaded.cfg == cfg
    with torch.no_grad():
        a, b = model(src, tgt), loaded(src, tgt)
    assert torch.equal(a.rotation, b.rotation)
    assert torch.equal(a.translation, b.translation)
    assert torch.equal(a.steps[-1].scores, b.steps[-1].scores)
    extra = read_checkpoint(tmp_path / "ck" / "model.pt")
    assert extra["note"] == "hello"
    assert extra["state"] == {"epoch": 3}
    assert [p.name for p in (tmp_path / "ck").iterdir()] == ["model.pt"]  # written atomically, no leftovers


def test_unknown_checkpoint_name_is_a_clear_error() -> None:
    with pytest.raises(FileNotFoundError, match="no-such-model"):
        resolve_checkpoint("no-such-model")


@pytest.mark.parametrize("device", [
    "meta",  # shapes and devices only: stands in for an accelerator on CPU-only machines
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
])
def test_a_training_step_keeps_every_tensor_on_the_model_device(device: str) -> None:
    torch.manual_seed(0)
    cfg = MFGNetConfig(**TINY)
    model = MFGNet(cfg).to(device).train()
    src, tgt, R, t = (x.to(device) for x in training_batch(3))
    src_idx, tgt_idx = sample_training_keypoints(src, tgt, R, t, 16, 16, cfg.match_threshold)  # no generator
    assert src_idx.device.type == tgt_idx.device.type == device
    out = model(src, tgt, src_idx=src_idx, tgt_idx=tgt_idx)
    total = registration_losses(out, src, tgt, R, t, cfg.match_threshold).total
    assert total.device.type == device
    total.backward()


def test_run_training_names_options_out_of_range_before_writing_anything(tmp_path) -> None:
    opts = TrainOptions(out=str(tmp_path / "run"), epochs=0, batch_size=0, lr=float("nan"), device="cpu")
    with pytest.raises(ValueError, match=r"epochs 0: must be 1 or more; batch_size 0: must be 1 or more; lr nan"):
        run_training(opts)
    assert not (tmp_path / "run").exists()
