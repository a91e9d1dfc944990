"""Training-side ``mfgnet`` sub-commands (loaded by ``service.cli`` through entry points)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from export.baselines import METHODS as BASELINES  # Open3D is imported only when one runs (the bench extra)
from model.data import SETTINGS, load_pairs, make_test_pairs, protocol_for, save_pairs
from model.recipes import recipe_draw
from service.search_mode import RotationSearchMode, rotation_search_from_options

Setting = Annotated[str, typer.Option(help=f"one of {', '.join(SETTINGS)}")]
SourcePoints = Annotated[int | None, typer.Option(help="source points kept after the crop (default: the crop size)")]
TargetPoints = Annotated[int | None, typer.Option(help="target points kept after the crop (default: the crop size)")]
Overlap = Annotated[float | None, typer.Option(help="fraction of each cloud kept by the crop, 0.5-1.0")]
Noise = Annotated[float | None, typer.Option(help="Gaussian noise sigma, clipped at +-5 sigma")]
MaxAngle = Annotated[float | None, typer.Option(help="largest Euler angle per axis in degrees, up to 180")]
Outliers = Annotated[
    float | None,
    typer.Option(help="share of each cloud's points replaced by uniform points in its bounding box, 0-0.5"),
]
ViewAngle = Annotated[
    float | None,
    typer.Option(help="scans: largest angle in degrees between the source's and the target's camera [default: 60]"),
]
Points = Annotated[
    int | None,
    typer.Option(help="points per cloud before the crop (default: the setting's; dense shapes allow up to 2048)"),
]


def setting_protocol(setting, source_points, target_points, overlap, noise, max_angle, points=None, outliers=None,
                     view_angle=None):
    """The setting's pair protocol with the command-line overrides, or a usage error."""
    try:
        return protocol_for(setting, source_points=source_points, target_points=target_points, overlap=overlap,
                            noise=noise, max_angle=max_angle, points=points, outliers=outliers, view_angle=view_angle)
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
    points: Points = None,
    outliers: Outliers = None,
    view_angle: ViewAngle = None,
) -> None:
    """Write seeded registration pairs (source, target, rotation, translation, label) to an npz."""
    protocol = setting_protocol(setting, source_points, target_points, overlap, noise, max_angle, points, outliers,
                                view_angle)
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
    outliers: Outliers = None,
    batches_per_epoch: Annotated[
        int | None, typer.Option(help="cap on batches per epoch (short epochs: validate and checkpoint more often)")
    ] = None,
    lr_drop_at: Annotated[float, typer.Option(help="fraction of the epochs after which lr is divided by 10")] = 0.8,
    recipe: Annotated[
        str | None,
        typer.Option(help="per-batch random training pairs: 'general' (independent sampling, noise, overlap, "
                     "density mismatch; --max-angle sets its rotation range); validation keeps --setting"),
    ] = None,
    views_share: Annotated[
        float | None,
        typer.Option(help="with --recipe: share of batches cut as two camera views (range scans, model.views), 0-1"),
    ] = None,
    data_workers: Annotated[
        int, typer.Option(min=1, help="on CUDA: processes making batches ahead of the GPU (views cost the most)")
    ] = 1,
) -> None:
    """Train MFGNet (CPU or CUDA) with periodic checkpoints and resume."""
    from model.train import TrainOptions
    from model.train import train as run

    setting_protocol(setting, source_points, target_points, overlap, noise, max_angle, None, outliers)  # fail early
    if views_share is not None and recipe is None:
        raise typer.BadParameter("--views-share needs --recipe")
    if recipe is not None:
        try:
            recipe_draw(recipe, max_angle, outliers, views_share)  # fail early, on the recipe's own checks
        except ValueError as err:
            raise typer.BadParameter(str(err)) from err
    opts = TrainOptions(
        setting=setting, out=str(out), epochs=epochs, batch_size=batch_size, lr=lr, weight_decay=weight_decay,
        seed=seed, resume=resume, init=init, patience=patience, max_minutes=max_minutes,
        checkpoint_minutes=checkpoint_minutes, device=device, data=data, threads=threads,
        config={"iterations": iterations, "share_weights": share_weights}, source_points=source_points,
        target_points=target_points, overlap=overlap, noise=noise, max_angle=max_angle, outliers=outliers,
        max_batches_per_epoch=batches_per_epoch, lr_drop_at=lr_drop_at, recipe=recipe, views_share=views_share,
        workers=data_workers,
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
    points: Points = None,
    outliers: Outliers = None,
    view_angle: ViewAngle = None,
    model: Annotated[
        str | None, typer.Option("--model", help="evaluate a bundled ONNX model (or model folder) through the runtime")
    ] = None,
    refine: Annotated[str, typer.Option(help="with --model: none, icp or icp-plane")] = "none",
    refine_points: Annotated[
        int | None, typer.Option(help="with --model: points per cloud the refinement uses [default: working clouds]")
    ] = None,
    rotation_search: Annotated[
        bool | None, typer.Option(help="with --model: always start from rotations covering SO(3) (= mode on)")
    ] = None,
    rotation_search_mode: Annotated[
        RotationSearchMode | None,
        typer.Option(help="with --model: off, on (= --rotation-search) or auto (search only where the plain "
                          "result looks wrong; reports the share of pairs searched) [default: off]"),
    ] = None,
    baseline: Annotated[
        str | None, typer.Option(help=f"classical method instead of a network: {', '.join(BASELINES)} (bench extra)")
    ] = None,
    per_pair: Annotated[
        Path | None, typer.Option(help="also write each pair's pose and errors here (.npz: rotation, translation, "
                                       "rotation_error_deg, translation_error, label when known; with --model "
                                       "also reliable and stability)")
    ] = None,
    by_label: Annotated[
        bool, typer.Option(help="add 'by_label': the recalls of each class (pairs with labels; ModelNet40 names)")
    ] = False,
) -> None:
    """The paper's metrics (RMSE/MAE of Euler angles and translation), isotropic errors, recall."""
    from model.metrics import registration_metrics, save_per_pair

    if sum(x is not None for x in (checkpoint, model, baseline)) != 1:
        raise typer.BadParameter(
            "give exactly one of --checkpoint (PyTorch), --model (ONNX runtime) or --baseline (Open3D)")
    if baseline is not None and baseline not in BASELINES:
        raise typer.BadParameter(f"unknown baseline {baseline!r}; expected one of {', '.join(BASELINES)}")
    if model is not None:
        from service.refine_modes import REFINE_MODES

        if refine not in REFINE_MODES:
            raise typer.BadParameter(f"unknown --refine {refine!r}; expected one of {', '.join(REFINE_MODES)}")
    try:
        search = rotation_search_from_options(rotation_search, rotation_search_mode) or False  # evaluate: off
    except ValueError as err:
        raise typer.BadParameter(str(err)) from err
    if pairs:
        data_pairs = load_pairs(pairs)
    else:
        protocol = setting_protocol(setting, source_points, target_points, overlap, noise, max_angle, points, outliers,
                                    view_angle)
        data_pairs = make_test_pairs(setting, "test", count, seed, data, protocol=protocol)
    if by_label and "label" not in data_pairs:
        raise typer.BadParameter("--by-label needs pairs with a 'label' array")
    if model is not None:
        from model.runtime_eval import runtime_poses

        run = runtime_poses(model, data_pairs, iterations, keypoints, refine, search, refine_points)
        R, t, secs = run.rotation, run.translation, run.seconds
    elif baseline is not None:
        from export.baselines import run_method

        R, t, secs = run_method(BASELINES[baseline], data_pairs, progress=True)
    else:
        from model.allocator import keep_freed_memory
        from model.checkpoint import load_model
        from model.inference import predict_poses

        keep_freed_memory()  # eager batches re-fault their freed buffers otherwise: ~2.4x slower (model.allocator)
        R, t, secs = predict_poses(load_model(checkpoint), data_pairs, batch_size, iterations, keypoints,
                                   progress=True)
    metrics = registration_metrics(R, t, data_pairs["rotation"], data_pairs["translation"], secs)
    if model is not None:
        from model.metrics import reliability_metrics

        metrics.update(reliability_metrics(R, t, data_pairs["rotation"], data_pairs["translation"], run.reliable))
        if search == "auto":
            metrics["rotation_search_share"] = run.searched / len(R)  # pairs on which "auto" ran the search
    if by_label:
        from model.data import class_names
        from model.metrics import recall_by_label

        metrics["by_label"] = recall_by_label(R, t, data_pairs["rotation"], data_pairs["translation"],
                                              data_pairs["label"], class_names(data))
    text = json.dumps(metrics, indent=2)
    typer.echo(text)
    if json_out:
        json_out.write_text(text + "\n")
    if per_pair:
        quality = {"reliable": run.reliable, "stability": run.stability} if model is not None else {}
        save_per_pair(per_pair, R, t, data_pairs, **quality)
