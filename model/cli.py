"""Training-side ``mfgnet`` sub-commands (loaded by ``service.cli`` through entry points)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from model.data import SETTINGS, load_pairs, make_test_pairs, protocol_for, save_pairs

Setting = Annotated[str, typer.Option(help=f"one of {', '.join(SETTINGS)}")]
SourcePoints = Annotated[int | None, typer.Option(help="source points kept after the crop (default: the crop size)")]
TargetPoints = Annotated[int | None, typer.Option(help="target points kept after the crop (default: the crop size)")]
Overlap = Annotated[float | None, typer.Option(help="fraction of each cloud kept by the crop, 0.5-1.0")]
Noise = Annotated[float | None, typer.Option(help="Gaussian noise sigma, clipped at +-5 sigma")]
MaxAngle = Annotated[float | None, typer.Option(help="largest Euler angle per axis in degrees, up to 180")]


def setting_protocol(setting, source_points, target_points, overlap, noise, max_angle):
    """The setting's pair protocol with the command-line overrides, or a usage error."""
    try:
        return protocol_for(setting, source_points=source_points, target_points=target_points, overlap=overlap,
                            noise=noise, max_angle=max_angle)
    except ValueError as err:
        raise typer.BadParameter(str(err)) from err


def make_pairs(
    out: Annotated[Path, typer.Option(help="output .npz")],
    setting: Setting = "clean",
    split: Annotated[str, typer.Option(help="train or test")] = "test",
    count: Annotated[int | None, typer.Option(help="number of pairs (default: one per shape)")] = None,
    seed: int = 0,
    data: Annotated[str | None, typer.Option(help="ModelNet40 directory ($MFGNET_DATA)")] = None,
    source_points: SourcePoints = None,
    target_points: TargetPoints = None,
    overlap: Overlap = None,
    noise: Noise = None,
    max_angle: MaxAngle = None,
) -> None:
    """Write seeded registration pairs (source, target, rotation, translation, label) to an npz."""
    protocol = setting_protocol(setting, source_points, target_points, overlap, noise, max_angle)
    try:
        pairs = make_test_pairs(setting, split, count, seed, data, protocol=protocol)
    except ValueError as err:
        raise typer.BadParameter(str(err)) from err
    save_pairs(out, pairs)
    typer.echo(f"wrote {len(pairs['source'])} {setting} pairs to {out}")


def train(
    setting: Setting = "clean",
    out: Annotated[Path, typer.Option(help="run directory (checkpoints, log.jsonl)")] = Path("runs/clean"),
    epochs: int = 50,
    batch_size: int = 8,
    lr: float = 1e-4,
    weight_decay: float = 1e-3,
    seed: int = 0,
    resume: Annotated[bool, typer.Option(help="continue from OUT/last.pt")] = False,
    init: Annotated[str | None, typer.Option(help="initial weights (fine-tuning)")] = None,
    patience: int = 10,
    max_minutes: float | None = None,
    checkpoint_minutes: float = 5.0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    data: str | None = None,
    threads: int | None = None,
    iterations: int = 4,
    share_weights: bool = False,
    source_points: SourcePoints = None,
    target_points: TargetPoints = None,
    overlap: Overlap = None,
    noise: Noise = None,
    max_angle: MaxAngle = None,
) -> None:
    """Train MFGNet (CPU or CUDA) with periodic checkpoints and resume."""
    from model.train import TrainOptions
    from model.train import train as run

    setting_protocol(setting, source_points, target_points, overlap, noise, max_angle)  # fail before loading data
    opts = TrainOptions(
        setting=setting, out=str(out), epochs=epochs, batch_size=batch_size, lr=lr, weight_decay=weight_decay,
        seed=seed, resume=resume, init=init, patience=patience, max_minutes=max_minutes,
        checkpoint_minutes=checkpoint_minutes, device=device, data=data, threads=threads,
        config={"iterations": iterations, "share_weights": share_weights}, source_points=source_points,
        target_points=target_points, overlap=overlap, noise=noise, max_angle=max_angle,
    )
    best = run(opts)
    typer.echo(f"best checkpoint: {best}")


def evaluate(
    checkpoint: Annotated[str | None, typer.Option(help="checkpoint path or bundled name")] = None,
    pairs: Annotated[Path | None, typer.Option(help="pairs .npz (else made from --setting)")] = None,
    setting: Setting = "clean",
    count: int | None = None,
    seed: int = 0,
    iterations: int | None = None,
    keypoints: int | None = None,
    batch_size: int = 16,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the metrics here")] = None,
    data: str | None = None,
    source_points: SourcePoints = None,
    target_points: TargetPoints = None,
    overlap: Overlap = None,
    noise: Noise = None,
    max_angle: MaxAngle = None,
) -> None:
    """The paper's metrics (RMSE/MAE of Euler angles and translation), isotropic errors, recall."""
    from model.checkpoint import load_model
    from model.inference import predict_poses
    from model.metrics import registration_metrics

    if checkpoint is None:
        raise typer.BadParameter("give --checkpoint")
    if pairs:
        data_pairs = load_pairs(pairs)
    else:
        protocol = setting_protocol(setting, source_points, target_points, overlap, noise, max_angle)
        data_pairs = make_test_pairs(setting, "test", count, seed, data, protocol=protocol)
    model = load_model(checkpoint)
    R, t, secs = predict_poses(model, data_pairs, batch_size, iterations, keypoints, progress=True)
    metrics = registration_metrics(R, t, data_pairs["rotation"], data_pairs["translation"], secs)
    text = json.dumps(metrics, indent=2)
    typer.echo(text)
    if json_out:
        json_out.write_text(text + "\n")
