"""``mfgnet evaluate``: the paper's metrics for a checkpoint, a bundled ONNX model or a classical baseline.

Registered as an ``mfgnet.commands`` entry point; the pair options are ``model.cli``'s.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Annotated

import typer

from bench.baselines import METHODS as BASELINES  # Open3D is imported only when one runs (the bench extra)
from bench.baselines import open3d_missing
from bench.report_io import machine_info, provenance
from model.cli import (
    MaxAngle,
    Noise,
    Outliers,
    Overlap,
    Points,
    Setting,
    SourcePoints,
    TargetPoints,
    ViewAngle,
    setting_pairs,
    setting_protocol,
)
from model.cli_inputs import (
    checkpoint_model,
    fail,
    given_options,
    model_dir,
    output_file,
    pairs_file,
)
from service.options import KEYPOINT_RANGE, MAX_ITERATIONS
from service.search_mode import RotationSearchMode, rotation_search_from_options


def evaluate(
    ctx: typer.Context,
    checkpoint: Annotated[str | None, typer.Option(help="checkpoint path or bundled name")] = None,
    pairs: Annotated[
        Path | None,
        typer.Option(
            help="pairs .npz, evaluated whole (else made from --setting, --count, --seed and the pair options)"
        ),
    ] = None,
    setting: Setting = "clean",
    count: Annotated[
        int | None,
        typer.Option(
            min=1,
            help="pairs to make from --setting: a seeded draw of the test split's shapes [default: one pair per shape]",
        ),
    ] = None,
    seed: Annotated[int, typer.Option(min=0, help="seed of the pairs made from --setting")] = 0,
    iterations: Annotated[
        int | None, typer.Option(min=1, max=MAX_ITERATIONS, help="network iterations [default: the model's]")
    ] = None,
    keypoints: Annotated[
        int | None,
        typer.Option(min=KEYPOINT_RANGE[0], max=KEYPOINT_RANGE[1], help="keypoints per cloud [default: the model's]"),
    ] = None,
    batch_size: Annotated[int, typer.Option(min=1, help="pairs per network batch (--checkpoint)")] = 16,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the metrics here")] = None,
    data: Annotated[
        str | None, typer.Option(help="ModelNet40 directory of --setting's test shapes ($MFGNET_DATA)")
    ] = None,
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
    refine: Annotated[str, typer.Option(help="with --model: none, icp, icp-plane or icp-plane-multistart")] = "none",
    refine_points: Annotated[
        int | None, typer.Option(help="with --model: points per cloud the refinement uses [default: working clouds]")
    ] = None,
    rotation_search: Annotated[
        bool | None, typer.Option(help="with --model: always start from rotations covering SO(3) (= mode on)")
    ] = None,
    rotation_search_mode: Annotated[
        RotationSearchMode | None,
        typer.Option(
            help="with --model: off, on (= --rotation-search) or auto (search only where the plain "
            "result looks wrong; reports the share of pairs searched) [default: off]"
        ),
    ] = None,
    baseline: Annotated[
        str | None, typer.Option(help=f"classical method instead of a network: {', '.join(BASELINES)} (bench extra)")
    ] = None,
    per_pair: Annotated[
        Path | None,
        typer.Option(
            help="also write each pair's pose and errors here (.npz: rotation, translation, "
            "rotation_error_deg, translation_error, label when known; with --model "
            "also reliable and stability)"
        ),
    ] = None,
    by_label: Annotated[
        bool, typer.Option(help="add 'by_label': the recalls of each class (pairs with labels; ModelNet40 names)")
    ] = False,
) -> None:
    """The paper's metrics (RMSE/MAE of Euler angles and translation), isotropic errors, recall; with them, under
    'evaluated', what was measured: the pairs, the checkpoint, model or baseline, the options it ran with, the machine
    and the code (``provenance``)."""
    from model.checkpoint import file_sha256
    from model.metrics import registration_metrics, save_per_pair

    if pairs is not None:
        refuse_pair_options(ctx)
    if sum(x is not None for x in (checkpoint, model, baseline)) != 1:
        raise typer.BadParameter(
            "give exactly one of --checkpoint (PyTorch), --model (ONNX runtime) or --baseline (Open3D)"
        )
    refuse_options_of_other_methods(ctx, checkpoint, model, baseline)
    if baseline is not None and baseline not in BASELINES:
        raise typer.BadParameter(f"unknown baseline {baseline!r}; expected one of {', '.join(BASELINES)}")
    if baseline is not None and (hint := open3d_missing()) is not None:
        raise typer.BadParameter(hint, param_hint="--baseline")
    if model is not None:
        from service.refine_modes import REFINE_MODES

        if refine not in REFINE_MODES:
            raise typer.BadParameter(f"unknown --refine {refine!r}; expected one of {', '.join(REFINE_MODES)}")
        if refine_points is not None:  # as mfgnet register checks them: before any pair runs, not a traceback
            from service.refine_modes import REFINE_POINTS_RANGE

            low, high = REFINE_POINTS_RANGE
            if not low <= refine_points <= high:
                fail(f"--refine-points {refine_points}: must be in {low}..{high}")
            if refine == "none":
                fail("--refine-points sets the refinement's clouds; --refine none runs no refinement")
    try:
        search = rotation_search_from_options(rotation_search, rotation_search_mode) or False  # evaluate: off
    except ValueError as err:
        raise typer.BadParameter(str(err)) from err
    for path, option in ((json_out, "--json"), (per_pair, "--per-pair")):
        if path is not None:
            output_file(path, option)
    checkpoint_path, _, network = checkpoint_model(checkpoint) if checkpoint is not None else (None, None, None)
    model_path = model_dir(model) if model is not None else None
    if pairs:
        data_pairs = pairs_file(pairs)
        evaluated: dict = {"pairs": {"file": str(pairs), "sha256": file_sha256(pairs)}}
    else:
        protocol = setting_protocol(
            setting, source_points, target_points, overlap, noise, max_angle, points, outliers, view_angle
        )
        data_pairs, shapes = setting_pairs(setting, "test", count, seed, data, protocol)
        evaluated = {
            "pairs": {
                "setting": setting,
                "split": "test",
                "count": count,
                "seed": seed,
                "protocol": asdict(protocol),
                "shapes": str(shapes),
            }
        }
    if checkpoint_path is not None:
        import torch

        evaluated |= {
            "checkpoint": str(checkpoint_path),
            "checkpoint_sha256": file_sha256(checkpoint_path),
            "iterations": iterations or network.cfg.iterations,
            "keypoints": keypoints or network.cfg.keypoints,
            "batch_size": batch_size,
        }
        threads = torch.get_num_threads()
    elif model_path is not None:
        from service.registrar import default_threads

        evaluated |= runtime_model_fields(model_path, iterations, keypoints)
        evaluated |= {"refine": refine, "refine_points": refine_points, "rotation_search": search}
        threads = default_threads()  # the Registrar's (bench.runtime_eval)
    else:
        evaluated["baseline"] = baseline
        from bench.real_scans import fpfh_threads

        threads = fpfh_threads()  # bench.baselines sets no thread count: Open3D's OpenMP default (OMP_NUM_THREADS)
    if "keypoints" in evaluated:  # a cloud of fewer points than the keypoints asked gives all of its points
        fewest = min(data_pairs["source"].shape[1], data_pairs["target"].shape[1])
        if evaluated["keypoints"] is not None and evaluated["keypoints"] > fewest:
            evaluated["keypoints_used"] = fewest
    # before the run: the shared checkout may move on during it (a checkpoint is named by its sha256 above)
    evaluated |= {"machine": machine_info(threads), "provenance": provenance([model_path] if model_path else [])}
    if by_label and "label" not in data_pairs:
        raise typer.BadParameter("--by-label needs pairs with a 'label' array")
    if model is not None:
        from bench.runtime_eval import runtime_poses

        run = runtime_poses(model_path, data_pairs, iterations, keypoints, refine, search, refine_points)
        R, t, secs = run.rotation, run.translation, run.seconds
    elif baseline is not None:
        from bench.baselines import run_method

        R, t, secs = run_method(BASELINES[baseline], data_pairs, progress=True)
    else:
        from model.allocator import keep_freed_memory
        from model.inference import predict_poses

        keep_freed_memory()  # eager batches re-fault their freed buffers otherwise: ~2.4x slower (model.allocator)
        R, t, secs = predict_poses(network, data_pairs, batch_size, iterations, keypoints, progress=True)
    metrics = registration_metrics(R, t, data_pairs["rotation"], data_pairs["translation"], secs)
    if model is not None:
        from model.metrics import reliability_metrics, warnings_by_outcome

        truth = data_pairs["rotation"], data_pairs["translation"]
        metrics.update(reliability_metrics(R, t, *truth, run.reliable))
        metrics["warnings_by_outcome"] = warnings_by_outcome(R, t, *truth, run.reliable, run.warnings)
        if search == "auto":
            metrics["rotation_search_share"] = run.searched / len(R)  # pairs on which "auto" ran the search
    if by_label:
        from model.data import class_names
        from model.metrics import recall_by_label

        names = (
            [str(name) for name in data_pairs["class_names"]]
            if "class_names" in data_pairs  # make-pairs'
            else class_names(data)
        )
        metrics["by_label"] = recall_by_label(
            R, t, data_pairs["rotation"], data_pairs["translation"], data_pairs["label"], names
        )
    metrics["evaluated"] = evaluated  # what these figures were measured on and with
    text = json.dumps(metrics, indent=2)
    typer.echo(text)
    if json_out:
        json_out.write_text(text + "\n")
    if per_pair:
        quality = {"reliable": run.reliable, "stability": run.stability} if model is not None else {}
        save_per_pair(per_pair, R, t, data_pairs, **quality)


# The options that only make pairs (from --setting); a --pairs file is evaluated whole, as it is.
PAIR_MAKING_OPTIONS = (
    "setting",
    "count",
    "seed",
    "source_points",
    "target_points",
    "overlap",
    "noise",
    "max_angle",
    "points",
    "outliers",
    "view_angle",
)


# The runtime's options (with --model), PyTorch's batches (with --checkpoint) and the network's (not --baseline).
RUNTIME_OPTIONS = ("refine", "refine_points", "rotation_search", "rotation_search_mode")
CHECKPOINT_OPTIONS = ("batch_size",)
NETWORK_OPTIONS = ("iterations", "keypoints")


def given_flags(ctx: typer.Context, names: tuple[str, ...]) -> list[str]:
    """The options of ``names`` the user gave (not defaults), as their flags."""
    given = given_options(ctx)
    return [param.opts[0] for param in ctx.command.params if param.name in names and param.name in given]


def refuse_pair_options(ctx: typer.Context) -> None:
    """A usage error naming the pair-making options given on the command line beside ``--pairs``.

    ``--count`` does not take the file's first pairs: files made from the whole test split are in class order,
    so their first pairs are a few classes only (``mfgnet make-pairs --count N --seed S`` makes a seeded subset).
    """
    given = given_flags(ctx, PAIR_MAKING_OPTIONS)
    if given:
        fail(
            f"{', '.join(given)}: cannot apply with --pairs ({'it makes' if len(given) == 1 else 'they make'} "
            "pairs from --setting; a --pairs file is evaluated whole; for a subset: mfgnet make-pairs --count N "
            "--seed S)"
        )


def refuse_options_of_other_methods(
    ctx: typer.Context, checkpoint: str | None, model: str | None, baseline: str | None
) -> None:
    """A usage error naming options given on the command line that the chosen method would ignore."""
    for names, applies, where in (
        (RUNTIME_OPTIONS, model is not None, "only with --model (the runtime)"),
        (CHECKPOINT_OPTIONS, checkpoint is not None, "only with --checkpoint (PyTorch)"),
        (NETWORK_OPTIONS, baseline is None, "to networks, not to --baseline"),
    ):
        given = [] if applies else given_flags(ctx, names)
        if given:
            fail(f"{', '.join(given)}: {'applies' if len(given) == 1 else 'apply'} {where}")


def runtime_model_fields(folder: Path, iterations: int | None, keypoints: int | None) -> dict:
    """The ``evaluated`` fields naming the ONNX model in ``folder``: name, version, its manifest's hash and the
    checkpoint it was exported from, and the iterations and keypoints it ran with."""
    from service.manifest import load_manifest

    manifest = load_manifest(folder)
    return {
        "model": manifest.name,
        "model_version": manifest.version,
        "model_directory": str(folder),
        "manifest_sha256": manifest.sha256,
        "checkpoint_sha256": manifest.raw.get("source_checkpoint_sha256"),
        "iterations": iterations or manifest.config.get("iterations"),
        "keypoints": keypoints or manifest.config.get("keypoints"),
    }
