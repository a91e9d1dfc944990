"""Training-side ``mfgnet`` sub-commands (loaded by ``service.cli`` through entry points): train, make-pairs,
make-dataset.

``mfgnet evaluate`` lives in ``bench.evaluate``; the pair options below are shared with it.
"""

from __future__ import annotations

import signal
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from model.cli_inputs import (
    checkpoint_model,
    fail,
    finite_shapes,
    given_options,
    input_file,
    json_file,
    output_file,
    output_folder,
    require_shapes,
)
from model.data import (
    DENSE_SETTINGS,
    SETTINGS,
    PairProtocol,
    class_names,
    make_test_pairs,
    pairs_path,
    protocol_for,
    save_pairs,
)
from model.recipes import recipe_draw

if TYPE_CHECKING:  # torch is imported only when a command trains
    from model.train import TrainOptions

Setting = Annotated[str, typer.Option(help=f"one of {', '.join(SETTINGS)}")]
TrainSetting = Annotated[str, typer.Option(
    help=f"one of {', '.join(s for s in SETTINGS if s not in DENSE_SETTINGS)} ({' and '.join(DENSE_SETTINGS)} have "
    "test shapes only)"
)]
SourcePoints = Annotated[int | None, typer.Option(help="source points kept after the crop (default: the crop size)")]
TargetPoints = Annotated[int | None, typer.Option(help="target points kept after the crop (default: the crop size)")]
Overlap = Annotated[float | None, typer.Option(help="fraction of each cloud kept by the crop, 0.5-1.0")]
Noise = Annotated[float | None, typer.Option(help="Gaussian noise sigma, 0-1, clipped at +-5 sigma")]
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


def setting_protocol(
    setting: str,
    source_points: int | None,
    target_points: int | None,
    overlap: float | None,
    noise: float | None,
    max_angle: float | None,
    points: int | None = None,
    outliers: float | None = None,
    view_angle: float | None = None,
) -> PairProtocol:
    """The setting's pair protocol with the command-line overrides, or a usage error."""
    try:
        return protocol_for(
            setting,
            source_points=source_points,
            target_points=target_points,
            overlap=overlap,
            noise=noise,
            max_angle=max_angle,
            points=points,
            outliers=outliers,
            view_angle=view_angle,
        )
    except ValueError as err:
        raise typer.BadParameter(str(err)) from err


def setting_pairs(
    setting: str, split: str, count: int | None, seed: int, data: str | None, protocol: PairProtocol
) -> tuple[dict[str, np.ndarray], Path]:
    """The seeded pairs of ``setting`` made from ``split``'s shapes under ``data`` (``--data``/``$MFGNET_DATA``) with
    ``protocol``, and the shapes file they come from (``make-pairs``, ``evaluate``); a missing or bad shapes file, a
    shape with NaN or infinite coordinates or a ``count`` NumPy cannot draw is a usage error."""
    shapes = require_shapes(split, setting, data)
    try:
        with finite_shapes():
            pairs = make_test_pairs(setting, split, count, seed, data, protocol=protocol)
    except ValueError as err:
        raise typer.BadParameter(str(err)) from err
    if count is not None and len(pairs["source"]) < count:  # else evaluate's 'evaluated' records a count it never ran
        raise typer.BadParameter(f"--count {count}: {shapes.name} holds {len(pairs['source'])} shapes, one pair each; "
                                 "give at most that many, or leave --count out")
    return pairs, shapes


def make_pairs(
    out: Annotated[Path, typer.Option(help="output .npz (added to a name without it)")],
    setting: Setting = "clean",
    split: Annotated[str, typer.Option(help="train or test")] = "test",
    count: Annotated[int | None, typer.Option(min=1, help="number of pairs (default: one per shape)")] = None,
    seed: Annotated[int, typer.Option(min=0, help="seed of the shapes drawn and the pairs made")] = 0,
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
    protocol = setting_protocol(
        setting, source_points, target_points, overlap, noise, max_angle, points, outliers, view_angle
    )
    output_file(out, "--out")
    out = output_file(pairs_path(out), "--out")  # the file written: numpy adds .npz to a name without it
    pairs, _ = setting_pairs(setting, split, count, seed, data, protocol)
    names = class_names(data)  # the data folder's: evaluate --by-label names the classes of the file's labels
    if names is not None:
        pairs["class_names"] = np.asarray(names, dtype=np.str_)
    written = save_pairs(out, pairs)
    typer.echo(f"wrote {len(pairs['source'])} {setting} pairs to {written}")


def make_dataset(
    ctx: typer.Context,
    src: Annotated[
        Path,
        typer.Argument(
            help="folder of shapes: one subfolder per class, or the shape files of one "
            "class; meshes (.obj .stl .off, .ply with faces) or point clouds"
        ),
    ],
    out: Annotated[
        Path,
        typer.Option(help="data folder to write, for train --data (and make-pairs, evaluate, export), or $MFGNET_DATA"),
    ],
    points: Annotated[
        int, typer.Option(min=1, help="points per shape (ModelNet40's files: 1024, what the settings' defaults need)")
    ] = 1024,
    dense_points: Annotated[
        int,
        typer.Option(
            min=0,
            help="points per test shape in the dense file (the dense and scans settings need 4096); 0: no dense file",
        ),
    ] = 4096,
    test_fraction: Annotated[
        float, typer.Option(help="share of each class's shapes held out for the test split, drawn with --seed")
    ] = 0.2,
    split_file: Annotated[
        Path | None,
        typer.Option(
            help="text file naming the test shapes, one per line, as paths "
            "below SRC (e.g. chair/a.obj); instead of --test-fraction"
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, help="seeds the surface samples, the subsets of clouds and the split")
    ] = 0,
    dtype: Annotated[
        str,
        typer.Option(
            help="storage: float32 (exact) or float16 (half the size; ModelNet40's, within 2.5e-4 in the unit ball)"
        ),
    ] = "float32",
    subsample: Annotated[
        str,
        typer.Option(
            help="clouds of more points than asked: random (a seeded subset, as "
            "ModelNet40's build) or fps (farthest-point sampling)"
        ),
    ] = "random",
    skip_bad: Annotated[
        bool,
        typer.Option(
            help="leave unreadable or degenerate shapes out (counted and listed in "
            "OUT/dataset.json) instead of stopping"
        ),
    ] = False,
    overwrite: Annotated[bool, typer.Option(help="replace the data files of a folder made before")] = False,
) -> None:
    """Make a data folder from your own shapes: each shape sampled (meshes: uniformly on the surface; clouds: a
    subset), centred and scaled into the unit ball as ModelNet40's, split into train and test per class."""
    from model import dataset as ds

    if dtype not in ds.DTYPES:
        fail(f"--dtype {dtype}: expected one of {', '.join(ds.DTYPES)}")
    if subsample not in ds.SUBSAMPLINGS:
        fail(f"--subsample {subsample}: expected one of {', '.join(ds.SUBSAMPLINGS)}")
    if split_file is not None and "test_fraction" in given_options(ctx):
        fail("--split-file and --test-fraction: give one (the split file names the test shapes)")
    if not 0 < test_fraction < 1:
        fail(f"--test-fraction {test_fraction}: must be above 0 and below 1 (each class needs train and test shapes)")
    if split_file is not None:
        input_file(split_file, "--split-file")
    if src.is_dir() and out.resolve().is_relative_to(src.resolve()):
        fail(f"--out {out}: inside SRC {src}, whose shapes it would then hold; choose a folder outside it")
    output_folder(out, "--out")
    existing = [name for name in ds.OUTPUT_FILES if (out / name).exists()]
    if existing and not overwrite:
        fail(
            f"--out {out}: holds a data folder already ({', '.join(existing)}); pass --overwrite to replace it, or "
            "choose another --out"
        )
    out.mkdir(parents=True, exist_ok=True)
    for name in existing:  # a dense file of an earlier set must not outlive it
        (out / name).unlink()

    def progress(items: list, what: str) -> object:
        from tqdm import tqdm

        return tqdm(items, desc=what, unit="shape", disable=None, mininterval=2)

    try:
        made = ds.build_dataset(
            src,
            out,
            points=points,
            dense_points=dense_points,
            seed=seed,
            test_fraction=None if split_file is not None else test_fraction,
            split_file=split_file,
            dtype=dtype,
            subsample=subsample,
            skip_bad=skip_bad,
            progress=progress,
        )
    except ds.DatasetError as err:
        fail(str(err))
    typer.echo(
        f"{len(made.classes)} class{'es' if len(made.classes) != 1 else ''} ({', '.join(made.classes[:8])}"
        f"{' ...' if len(made.classes) > 8 else ''}): {len(made.train)} train and {len(made.test)} test shapes "
        f"of {points} points"
    )
    if dense_points:
        left = len(made.test) - len(made.dense)
        typer.echo(
            f"dense test file: {len(made.dense)} shape{'s' if len(made.dense) != 1 else ''} of {dense_points} "
            "points"
            + (f" ({left} clouds of fewer points left out)" if left else "")
            + ("" if made.dense else ": none, so no dense file (the dense and scans settings need one)")
        )
    if made.skipped:
        first = next(iter(made.skipped.items()))
        typer.echo(
            f"skipped {len(made.skipped)} unusable shape{'s' if len(made.skipped) != 1 else ''} "
            f"(e.g. {first[0]}: {first[1]}); all listed in {out / 'dataset.json'}",
            err=True,
        )
    if made.ignored:
        typer.echo(f"left alone {made.ignored} file{'s' if made.ignored != 1 else ''} of other suffixes", err=True)
    typer.echo(f"unseen setting: {ds.unseen_note(made.classes)}")
    typer.echo(f"wrote {out}: use it as --data {out} (or MFGNET_DATA={out})")


# `mfgnet train` options that make a run -> their TrainOptions field (model.train.RUN_OPTIONS): with --resume, one left
# out takes the run's value and one given must equal it; --iterations / --share-weights must equal the checkpoint's.
RUN_OPTION_FIELDS = {
    "setting": "setting",
    "seed": "seed",
    "batch_size": "batch_size",
    "batches_per_epoch": "max_batches_per_epoch",
    "lr": "lr",
    "weight_decay": "weight_decay",
    "lr_drop_at": "lr_drop_at",
    "val_pairs": "val_pairs",
    "source_points": "source_points",
    "target_points": "target_points",
    "overlap": "overlap",
    "noise": "noise",
    "max_angle": "max_angle",
    "outliers": "outliers",
    "recipe": "recipe",
    "views_share": "views_share",
    "sensor_share": "sensor_share",
    "init": "init",
}
TRAIN_FLAGS = {"max_batches_per_epoch": "batches_per_epoch", "workers": "data_workers"}  # field -> option, if unlike
GROWING_OPTIONS = ("epochs", "patience")  # with --resume: given, they extend (or shorten) the run; left out, the run's


def resumed_options(ctx: typer.Context, opts: TrainOptions, checkpoint: dict) -> TrainOptions:
    """``opts`` of ``mfgnet train --resume`` made the run's: each run option left out takes the saved value (its
    ``config.json``, the network from ``last.pt``); a usage error names those given with another value."""
    from model.train import RUN_OPTIONS, checkpoint_run_options

    out = Path(opts.out)
    saved = checkpoint_run_options(checkpoint)  # no config.json (a device run's folder): what last.pt records
    if (out / "config.json").exists():
        config = json_file(out / "config.json", "--resume")
        if not isinstance(config, dict) or not isinstance(config.get("train"), dict):
            fail(f"--resume {out / 'config.json'}: not a run's config (no 'train' options)")
        saved = config["train"]
    saved = {"setting": checkpoint.get("setting", opts.setting), **saved}
    given = given_options(ctx)
    conflicts = []
    for name, field in RUN_OPTION_FIELDS.items():
        if field not in saved:
            continue
        if name in given and getattr(opts, field) != saved[field]:
            conflicts.append(f"--{name.replace('_', '-')} {getattr(opts, field)} (the run's: {saved[field]})")
        setattr(opts, field, saved[field])
    for field in set(RUN_OPTIONS) - set(RUN_OPTION_FIELDS.values()):  # no command-line option: the run's
        if field in saved:
            setattr(opts, field, saved[field])
    network = checkpoint["config"]
    for name in ("iterations", "share_weights"):  # the network: the checkpoint's
        if name in given and opts.config[name] != network.get(name):
            conflicts.append(f"--{name.replace('_', '-')} {opts.config[name]} (the run's: {network.get(name)})")
    if conflicts:
        fail(
            f"--resume {out}: {', '.join(conflicts)}: a resumed run keeps its options; leave them out, or start a "
            "new run with another --out"
        )
    opts.config = dict(network)
    for field in GROWING_OPTIONS:
        if field not in given and field in saved:
            setattr(opts, field, saved[field])
    return opts


def train(
    ctx: typer.Context,
    setting: TrainSetting = "clean",
    out: Annotated[Path, typer.Option(help="run directory (checkpoints, log.jsonl)")] = Path("runs/clean"),
    epochs: Annotated[int, typer.Option(help="epochs of the run (with --resume: left out, the run's)")] = 50,
    batch_size: Annotated[int, typer.Option(help="pairs per training batch")] = 8,
    lr: Annotated[float, typer.Option(help="Adam's learning rate (divided by 10 at --lr-drop-at)")] = 1e-4,
    weight_decay: Annotated[float, typer.Option(help="Adam's weight decay")] = 1e-3,
    seed: Annotated[
        int, typer.Option(help="seeds the initial weights, the validation split and pairs, and every batch")
    ] = 0,
    resume: Annotated[
        bool,
        typer.Option(help="continue the run in OUT from its last.pt with its options (a new run where OUT holds none)"),
    ] = False,
    init: Annotated[
        str | None,
        typer.Option("--init", "--init-from", help="initial weights (fine-tuning): a checkpoint file or bundled name"),
    ] = None,
    patience: Annotated[
        int,
        typer.Option(
            help="epochs without a better validation MAE(R) before stopping (with --resume: left out, the run's)"
        ),
    ] = 10,
    max_minutes: Annotated[
        float | None,
        typer.Option(
            help="stop after the step that passes this many minutes of this process, with "
            "OUT/last.pt written (exit 0; --resume continues)"
        ),
    ] = None,
    checkpoint_minutes: Annotated[
        float, typer.Option(help="write OUT/last.pt every this many minutes inside an epoch (and after each epoch)")
    ] = 5.0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    data: Annotated[str | None, typer.Option(help="ModelNet40 directory ($MFGNET_DATA)")] = None,
    threads: Annotated[int | None, typer.Option(help="torch CPU threads (default: torch's)")] = None,
    iterations: Annotated[
        int, typer.Option(help="network iterations (matching + SVD); with --init or --resume: the checkpoint's")
    ] = 4,
    share_weights: Annotated[
        bool, typer.Option(help="one matcher set for every iteration; with --init or --resume: the checkpoint's")
    ] = False,
    source_points: SourcePoints = None,
    target_points: TargetPoints = None,
    overlap: Overlap = None,
    noise: Noise = None,
    max_angle: MaxAngle = None,
    outliers: Outliers = None,
    batches_per_epoch: Annotated[
        int | None, typer.Option(help="cap on batches per epoch (short epochs: validate and checkpoint more often)")
    ] = None,
    lr_drop_at: Annotated[
        float,
        typer.Option(
            help="lr is divided by 10 from epoch floor(LR_DROP_AT x epochs) on, never before epoch 1 "
            "(a one-epoch run keeps --lr); 1 or more: never"
        ),
    ] = 0.8,
    recipe: Annotated[
        str | None,
        typer.Option(
            help="per-batch random training pairs: 'general' (independent sampling, noise, overlap, "
            "density mismatch; --max-angle sets its rotation range; validation keeps --setting), "
            "'real' (general at any orientation with simulated sensor pairs, model.sensor_pairs; "
            "validation on sensor pairs) or 'search' (real at the rotation search's 128 points per "
            "cloud and rotations within 65 deg)"
        ),
    ] = None,
    views_share: Annotated[
        float | None,
        typer.Option(help="with --recipe: share of batches cut as two camera views (range scans, model.views), 0-1"),
    ] = None,
    sensor_share: Annotated[
        float | None,
        typer.Option(help="with --recipe: share of batches of simulated sensor pairs (model.sensor_pairs), 0-1"),
    ] = None,
    val_pairs: Annotated[int, typer.Option(min=1, help="validation pairs per epoch (held-out training shapes)")] = 256,
    data_workers: Annotated[
        int, typer.Option(min=1, help="on CUDA: processes making batches ahead of the GPU (views cost the most)")
    ] = 1,
    snapshot_every: Annotated[
        int,
        typer.Option(
            min=0,
            help="keep the weights after every N-th epoch (OUT/snapshots/), to choose on real "
            "scans; 0: only best.pt and last.pt",
        ),
    ] = 0,
) -> None:
    """Train MFGNet (CPU or CUDA) with periodic checkpoints and resume.

    SIGTERM or SIGINT stops the run after the current step with OUT/last.pt written (--resume continues it) and exits
    with 128 + the signal's number (143, 130); a run that ends (its epochs, --patience, --max-minutes) exits with 0.
    """
    from model.train import (
        RunFolderInUseError,
        TooFewShapesError,
        TrainOptions,
        check_run_folder,
        init_config,
        option_problems,
        run_training,
    )

    output_folder(out, "--out")
    opts = TrainOptions(
        setting=setting,
        out=str(out),
        epochs=epochs,
        batch_size=batch_size,
        lr=lr,
        weight_decay=weight_decay,
        seed=seed,
        resume=resume,
        init=init,
        patience=patience,
        max_minutes=max_minutes,
        checkpoint_minutes=checkpoint_minutes,
        device=device,
        data=data,
        threads=threads,
        config={"iterations": iterations, "share_weights": share_weights},
        source_points=source_points,
        target_points=target_points,
        overlap=overlap,
        noise=noise,
        max_angle=max_angle,
        outliers=outliers,
        max_batches_per_epoch=batches_per_epoch,
        lr_drop_at=lr_drop_at,
        recipe=recipe,
        views_share=views_share,
        sensor_share=sensor_share,
        val_pairs=val_pairs,
        workers=data_workers,
        snapshot_every=snapshot_every,
    )
    try:  # the library's check (no --overwrite here: a run is replaced by hand)
        run_files = check_run_folder(out, resume)
    except RunFolderInUseError as err:
        if err.resume:
            fail(
                f"--resume {out}: holds a run ({', '.join(err.files)}) but no last.pt to continue it from; choose "
                "another --out"
            )
        fail(
            f"--out {out}: holds a run already ({', '.join(err.files)}); pass --resume to continue it, or choose "
            "another --out"
        )
    if resume and run_files:
        resume_from, checkpoint, _ = checkpoint_model(out / "last.pt", "--resume")
        missing = [key for key in ("optimizer", "state") if key not in checkpoint]
        if missing:
            fail(f"--resume {resume_from}: no {' or '.join(map(repr, missing))} to resume from")
        opts = resumed_options(ctx, opts, checkpoint)
    problems = option_problems(opts)  # values out of range: a usage error naming each, not a traceback or empty run
    if problems:
        fail("; ".join(f"--{TRAIN_FLAGS.get(name, name).replace('_', '-')} {why}" for name, why in problems.items()))
    setting_protocol(
        opts.setting,
        opts.source_points,
        opts.target_points,
        opts.overlap,
        opts.noise,
        opts.max_angle,
        None,
        opts.outliers,
    )  # fail early
    require_shapes("train", opts.setting, data)
    if (opts.views_share is not None or opts.sensor_share is not None) and opts.recipe is None:
        raise typer.BadParameter("--views-share and --sensor-share need --recipe")
    if opts.recipe is not None:
        try:  # fail early, on the recipe's checks
            recipe_draw(opts.recipe, opts.max_angle, opts.outliers, opts.views_share, opts.sensor_share)
        except ValueError as err:
            raise typer.BadParameter(str(err)) from err
    if init is not None and not (resume and run_files):  # fine-tuning continues the checkpoint's network
        init_path, init_data, _ = checkpoint_model(init, "--init")  # its weights fit its own config
        given = given_options(ctx)
        _, conflicts = init_config(
            {name: opts.config[name] for name in ("iterations", "share_weights") if name in given}, init_data["config"]
        )
        if conflicts:
            fail(
                f"--init {init_path}: "
                + ", ".join(f"--{c.replace('_', '-', 1)}" for c in conflicts)
                + ": fine-tuning keeps the checkpoint's network; leave these out or give its values"
            )
        opts.config = dict(init_data["config"])
    try:
        with finite_shapes():  # checked as run_training loads them, before its first batch
            outcome = run_training(opts)
    except TooFewShapesError as err:
        fail(f"{'--data' if data else '$MFGNET_DATA'} {err}")
    if outcome.stopped_by:
        code = 128 + signal.Signals[outcome.stopped_by].value
        typer.echo(
            f"mfgnet: stopped on {outcome.stopped_by} before the run's end (exit {code}); "
            f"--resume --out {out} continues from {out / 'last.pt'}",
            err=True,
        )
        raise typer.Exit(code)
    if outcome.best is None and outcome.timed_out and not outcome.epochs:  # a time box shorter than an epoch
        typer.echo(f"no best checkpoint yet: --max-minutes ended the run before its first validation; --resume --out "
                   f"{out} continues from {out / 'last.pt'}")
        return
    if outcome.best is None:  # a failed run: nothing to fine-tune, export or evaluate from
        why = (
            f"none of its {outcome.epochs} epochs had a finite validation MAE(R) (NaN or inf) from finite weights"
            if outcome.epochs
            else "it stopped before its first validation"
        )
        typer.echo(f"mfgnet: no best checkpoint: {why}; no {out / 'best.pt'} was written", err=True)
        raise typer.Exit(1)
    typer.echo(f"best checkpoint: {outcome.best}")
