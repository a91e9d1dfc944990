"""Training loop: Adam, step learning-rate drop, periodic + best checkpoints, resume, JSONL log."""

from __future__ import annotations

import json
import math
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from model.allocator import keep_freed_memory
from model.checkpoint import file_sha256, read_checkpoint, resolve_checkpoint, save_checkpoint
from model.config import MFGNetConfig
from model.data import PairProtocol, TrainPairStream, load_shapes, make_pairs, protocol_for, shapes_file
from model.graceful_stop import GracefulStop
from model.inference import predict_poses
from model.losses import registration_losses, sample_training_keypoints
from model.metrics import registration_metrics
from model.network import MFGNet
from model.provenance import portable_path, run_record
from model.recipes import SEARCH, recipe_draw
from model.sensor_pairs import validation_pairs as sensor_validation_pairs


@dataclass
class TrainOptions:
    setting: str = "clean"
    out: str = "runs/clean"
    epochs: int = 50
    batch_size: int = 8
    lr: float = 1e-4
    weight_decay: float = 1e-3
    lr_drop_at: float = 0.8  # lr / 10 from epoch floor(lr_drop_at x epochs) on, never before epoch 1 (lr_at)
    seed: int = 0
    val_fraction: float = 0.04  # training shapes held out for validation
    val_pairs: int = 256
    checkpoint_minutes: float = 5.0
    patience: int = 10  # epochs without validation improvement before stopping
    max_minutes: float | None = None  # stop (after a checkpoint) when this much time has passed
    max_batches_per_epoch: int | None = None
    resume: bool = False  # continue the run in ``out`` from its last.pt (a new run where ``out`` holds none)
    overwrite: bool = False  # start a new run in ``out`` even where it holds one, deleting that run's files first
    init: str | None = None  # start from these weights (fine-tuning), fresh optimizer
    device: str = "auto"
    data: str | None = None
    threads: int | None = None
    config: dict = field(default_factory=dict)  # MFGNetConfig overrides
    # pair-protocol overrides of the setting (model.data.protocol_for); None keeps the setting's value
    source_points: int | None = None
    target_points: int | None = None
    overlap: float | None = None
    noise: float | None = None
    max_angle: float | None = None
    outliers: float | None = None  # share of scattered points per cloud (with a recipe: the largest drawn)
    recipe: str | None = None  # per-batch random protocols for training (model.recipes); validation keeps the setting's
    views_share: float | None = None  # with a recipe: its share of batches cut as camera views (model.views)
    sensor_share: float | None = None  # with a recipe: its share of simulated sensor batches (model.sensor_pairs)
    prefetch: bool | None = None  # make batches in worker processes while the model trains; None: on for CUDA
    workers: int = 1  # with prefetch: processes making batches (camera-view pairs take ~4 ms each to make)
    snapshot_every: int = 0  # keep the weights after every this many epochs (snapshots/epoch_NNNN.pt); 0: none

    def pair_protocol(self) -> PairProtocol:
        """The training / validation pair protocol: the setting's, with these overrides."""
        return protocol_for(self.setting, source_points=self.source_points, target_points=self.target_points,
                            overlap=self.overlap, noise=self.noise, max_angle=self.max_angle, outliers=self.outliers)


def option_problems(opts: TrainOptions) -> dict[str, str]:
    """The options of ``opts`` out of range, each field's name (``config`` ones as ``iterations``) -> what it must be.

    Empty where every option is valid; checked before a run reads or writes anything, so that a bad value is an error
    naming it, not a traceback from Adam, a division by zero, or a run that trains no batch and writes no ``best.pt``.
    """

    def number(value: object) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value)

    def at_least(value: object, low: float, above: bool = False, finite: bool = False) -> bool:
        return number(value) and (value > low if above else value >= low) and (not finite or value < math.inf)

    checks = {  # field -> (value, valid, what it must be)
        "epochs": (opts.epochs, at_least(opts.epochs, 1), "1 or more"),
        "batch_size": (opts.batch_size, at_least(opts.batch_size, 1), "1 or more"),
        "lr": (opts.lr, at_least(opts.lr, 0, above=True, finite=True), "a finite number above 0"),
        "weight_decay": (opts.weight_decay, at_least(opts.weight_decay, 0, finite=True), "a finite number, 0 or more"),
        "lr_drop_at": (opts.lr_drop_at, at_least(opts.lr_drop_at, 0), "0 or more (1 or more: never)"),
        "patience": (opts.patience, at_least(opts.patience, 1), "1 or more"),
        "val_pairs": (opts.val_pairs, at_least(opts.val_pairs, 1), "1 or more"),
        "val_fraction": (opts.val_fraction, at_least(opts.val_fraction, 0, above=True) and opts.val_fraction < 1,
                         "between 0 and 1"),
        "checkpoint_minutes": (opts.checkpoint_minutes, at_least(opts.checkpoint_minutes, 0), "0 or more"),
        "max_minutes": (opts.max_minutes, opts.max_minutes is None or at_least(opts.max_minutes, 0, above=True),
                        "above 0"),
        "max_batches_per_epoch": (opts.max_batches_per_epoch, opts.max_batches_per_epoch is None
                                  or at_least(opts.max_batches_per_epoch, 1), "1 or more"),
        "threads": (opts.threads, opts.threads is None or at_least(opts.threads, 1), "1 or more"),
        "workers": (opts.workers, at_least(opts.workers, 1), "1 or more"),
        "snapshot_every": (opts.snapshot_every, at_least(opts.snapshot_every, 0), "0 or more"),
    }
    iterations = opts.config.get("iterations", MFGNetConfig.iterations)
    from service.request_defaults import MAX_ITERATIONS  # what an exported model may default to

    checks["iterations"] = (iterations, at_least(iterations, 1) and iterations <= MAX_ITERATIONS,
                            f"1 to {MAX_ITERATIONS}")
    problems = {name: f"{value}: must be {rule}" for name, (value, ok, rule) in checks.items() if not ok}
    try:
        device = torch.device("cpu" if opts.device == "auto" else opts.device)
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        problems["device"] = f"{opts.device}: must be auto, cpu or cuda (cuda:N)"
    elif device.type == "cuda" and not torch.cuda.is_available():
        problems["device"] = f"{opts.device}: no CUDA device here (auto or cpu)"
    return problems


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def split_validation(n: int, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic train / validation split of ``n`` shape indices."""
    rng = np.random.default_rng([seed, 7919])
    perm = rng.permutation(n)
    n_val = max(1, round(n * fraction))
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


def epoch_batches(
    stream: TrainPairStream, epoch: int, batch_size: int, prefetch: bool, first: int = 0, workers: int = 1
) -> Iterator[dict[str, np.ndarray]] | torch.utils.data.DataLoader[dict[str, torch.Tensor]]:
    """One epoch's batches from batch ``first`` on, made here or (``prefetch``) in ``workers`` processes ahead.

    Worker ``i`` makes every ``workers``-th batch of the same seeded stream, starting with ``first + i``, and the
    loader takes one from each worker in turn, so every way yields the same batches in the same order.
    """
    if not prefetch:
        return stream.epoch(epoch, batch_size, first)

    class _Epoch(torch.utils.data.IterableDataset):
        def __iter__(self):
            info = torch.utils.data.get_worker_info()
            return stream.epoch(epoch, batch_size, first, (info.id, info.num_workers))

    return torch.utils.data.DataLoader(_Epoch(), batch_size=None, num_workers=workers, prefetch_factor=4)


RUN_FILES = ("last.pt", "best.pt", "log.jsonl", "snapshots")  # what a run leaves in its folder (config.json: at start)


class TooFewShapesError(ValueError):
    """The training shapes (after the validation split) make no batch: every epoch would end without a step and the
    run's checkpoint would be its initial weights."""


class RunFolderInUseError(FileExistsError):
    """Training into ``out`` would overwrite the run it holds (its ``files``, of :data:`RUN_FILES`): a new run
    (``resume`` false) without ``overwrite``, or a resumed one where there is no ``last.pt`` to continue from."""

    def __init__(self, out: Path, files: list[str], resume: bool) -> None:
        self.out, self.files, self.resume = out, files, resume
        if resume:
            why = (f"{out} holds a run ({', '.join(files)}) but no last.pt to resume it from; choose another out, or "
                   "pass overwrite (without resume) to replace the run")
        else:
            why = (f"{out} holds a run already ({', '.join(files)}); pass resume to continue it, overwrite to replace "
                   "it, or choose another out")
        super().__init__(why)


def check_run_folder(out: Path, resume: bool, overwrite: bool = False) -> list[str]:
    """The run files (:data:`RUN_FILES`) that ``out`` holds, where training into it keeps every run: it holds none,
    or ``resume`` has a ``last.pt`` to continue from; with ``overwrite`` (not with ``resume``) those files are the run
    to replace. Else :class:`RunFolderInUseError`; ``mfgnet train`` turns it into its usage error (``--resume``)."""
    if resume and overwrite:
        raise ValueError(f"training {out}: resume and overwrite exclude each other (continue the run, or replace it)")
    files = [name for name in RUN_FILES if (Path(out) / name).exists()]
    if files and not overwrite and (not resume or "last.pt" not in files):
        raise RunFolderInUseError(Path(out), files, resume)
    return files


def remove_run(out: Path, files: list[str]) -> None:
    """Delete the run files ``files`` (of :data:`RUN_FILES`) from ``out``: a replaced run leaves no log records,
    checkpoints or snapshots behind to be taken for the new run's."""
    for name in files:
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


# What makes a run: a resumed run must keep these (``resume_conflicts``); the rest are this process's (device, data,
# threads, workers, prefetch, time limits, snapshots) or may grow a run (epochs, patience).
RUN_OPTIONS = ("setting", "seed", "batch_size", "max_batches_per_epoch", "lr", "weight_decay", "lr_drop_at",
               "val_fraction", "val_pairs", "source_points", "target_points", "overlap", "noise", "max_angle",
               "outliers", "recipe", "views_share", "sensor_share", "init")


def checkpoint_run_options(ckpt: dict) -> dict:
    """The run's options as its checkpoint records them (``provenance``: the latest resume's, else the start's), for
    a run folder without ``config.json`` (``scripts/device_train.py`` removes it); empty where it records none."""
    made_by = ckpt.get("provenance") if isinstance(ckpt.get("provenance"), dict) else {}
    for record in (*reversed(made_by.get("resumes") or []), made_by.get("run")):
        if isinstance(record, dict) and isinstance(record.get("options"), dict):
            return dict(record["options"])
    return {}


def resume_conflicts(opts: TrainOptions, saved: dict, saved_network: MFGNetConfig) -> list[str]:
    """The options of ``opts`` that differ from those of the run being resumed: ``saved`` (its ``config.json``
    ``train`` options; only the keys it holds are compared) and ``saved_network`` (its checkpoint's network)."""
    given = asdict(opts)
    conflicts = [name for name in RUN_OPTIONS if name in saved and saved[name] != given[name]]
    if MFGNetConfig.from_dict({**MFGNetConfig().to_dict(), **opts.config}) != saved_network:
        conflicts.append("config")
    return conflicts


def init_config(overrides: dict, saved: dict) -> tuple[MFGNetConfig, list[str]]:
    """The network of a run fine-tuned from a checkpoint whose config is ``saved``: that network, and the
    ``overrides`` (``TrainOptions.config`` entries) that contradict it, each as ``name value (the checkpoint's: x)``.

    Fine-tuning continues the checkpoint's network; an override may only repeat the checkpoint's value.
    """
    cfg = MFGNetConfig.from_dict({**MFGNetConfig().to_dict(), **saved})
    conflicts = [f"{name} {value} (the checkpoint's: {getattr(cfg, name, None)})" for name, value in overrides.items()
                 if getattr(cfg, name, None) != value]
    return cfg, conflicts


def lr_at(opts: TrainOptions, epoch: int) -> float:
    """The learning rate of ``epoch``: ``lr``, divided by 10 from epoch floor(lr_drop_at x epochs) on, but never
    before epoch 1, so that a one-epoch run trains at ``lr``."""
    drop = max(1, math.floor(opts.lr_drop_at * opts.epochs))
    return opts.lr * (0.1 if epoch >= drop else 1.0)


def batch_generator(seed: int, epoch: int, batch: int) -> torch.Generator:
    """The generator of batch ``batch``'s own random draws (its training keypoints), from (seed, epoch, batch) only.

    A CPU generator on every device (``sample_training_keypoints`` draws on the CPU), so a resumed run, a CUDA run
    and an uninterrupted CPU run draw the same keypoints for the same batch.
    """
    state = np.random.SeedSequence([seed, epoch, batch, 15485863]).generate_state(2, np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))


@dataclass
class TrainOutcome:
    best: Path | None  # the best checkpoint (best.pt); None where no epoch had a finite validation MAE(R) and weights
    stopped_by: str | None = None  # the signal (SIGTERM, SIGINT) that stopped the run before its end; --resume goes on
    epochs: int = 0  # epochs the run has finished (validated), its earlier tries' included
    timed_out: bool = False  # stopped by max_minutes before the run's end; --resume goes on


def train(opts: TrainOptions) -> Path | None:
    """Train (or resume) a model; returns the path of the best checkpoint, ``None`` where no epoch had a finite
    validation MAE(R) (``run_training`` also says how it ended).

    Like ``mfgnet train``, it refuses (:class:`RunFolderInUseError`, a ``FileExistsError``) an ``opts.out`` that holds a
    run, unless ``opts.resume`` continues it or ``opts.overwrite`` replaces it (:func:`check_run_folder`).
    """
    return run_training(opts).best


def run_training(opts: TrainOptions) -> TrainOutcome:
    """Train (or resume) a model: its best checkpoint, and the signal that stopped it early, if one did.

    Before anything is read or written, options out of range (:func:`option_problems`) are a ``ValueError`` naming
    them, and a folder that holds a run is refused (:class:`RunFolderInUseError`) unless ``opts.resume`` continues it
    or ``opts.overwrite`` replaces it (its files deleted once the new run is set up).
    A stop signal (SIGTERM, SIGINT) ends the run after the step it arrives in, with ``last.pt`` written; a run ended by
    ``max_minutes`` or ``patience`` ends as asked (``stopped_by`` ``None``).
    """
    problems = option_problems(opts)  # before anything is read or written
    if problems:
        raise ValueError(f"training {opts.out}: " + "; ".join(f"{name} {why}" for name, why in problems.items()))
    out = Path(opts.out)
    run_files = check_run_folder(out, opts.resume, opts.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    if opts.threads:
        torch.set_num_threads(opts.threads)
    device = pick_device(opts.device)
    if device.type == "cpu":
        keep_freed_memory()  # reuse the step's large buffers instead of re-faulting them (model.allocator)
    torch.manual_seed(opts.seed)

    protocol = opts.pair_protocol()
    shapes, _ = load_shapes("train", opts.setting, opts.data)
    data_file = shapes_file("train", opts.setting, opts.data)
    train_idx, val_idx = split_validation(len(shapes), opts.val_fraction, opts.seed)
    draw = (recipe_draw(opts.recipe, opts.max_angle, opts.outliers, opts.views_share, opts.sensor_share)
            if opts.recipe else protocol)
    stream = TrainPairStream(shapes[train_idx], draw, opts.seed)
    if stream.batches_per_epoch(opts.batch_size) == 0:
        resumed = opts.resume and "last.pt" in run_files  # --resume where out holds no run starts a new one
        mend = ("a resumed run keeps its batch size: resume on the run's data, or start a new run" if resumed
                else "add shapes or lower --batch-size")
        raise TooFewShapesError(f"{data_file.parent}: {len(train_idx)} training shapes ({len(val_idx)} of "
                                f"{len(shapes)} held out to validate) make no batch of {opts.batch_size}: {mend}")
    val_shapes = shapes[val_idx][: opts.val_pairs]
    if len(val_shapes) < opts.val_pairs:  # one pair per held-out shape: a small data folder holds out few
        print(f"validating on {len(val_shapes)} pairs, not {opts.val_pairs} (val_pairs): one per held-out shape, "
              f"{len(val_idx)} of the {len(shapes)} training shapes (val_fraction {opts.val_fraction})")
    if opts.recipe == "real":  # checkpoints chosen on simulated sensor pairs over the training rotations
        val_pairs = sensor_validation_pairs(val_shapes, opts.seed, max_angle_deg=opts.max_angle or 180.0)
    elif opts.recipe == "search":  # ... at the search's rows per cloud and rotations
        val_pairs = sensor_validation_pairs(val_shapes, opts.seed, counts=SEARCH.cloud_points,
                                            max_angle_deg=opts.max_angle or SEARCH.max_angle_deg)
    else:
        val_pairs = make_pairs(val_shapes, protocol, np.random.default_rng([opts.seed, 104729]))

    last_path, best_path, log_path = out / "last.pt", out / "best.pt", out / "log.jsonl"
    # "partial": the sums of an epoch stopped inside (losses, batches, seconds), so that its record covers all of it
    state = {"epoch": 0, "batch": 0, "best": float("inf"), "best_epoch": -1, "stale": 0, "partial": None}
    if opts.resume and last_path.exists():
        ckpt = read_checkpoint(last_path)
        cfg = MFGNetConfig.from_dict(ckpt["config"])
        saved = (json.loads((out / "config.json").read_text())["train"] if (out / "config.json").exists()
                 else checkpoint_run_options(ckpt))
        conflicts = resume_conflicts(opts, {"setting": ckpt.get("setting", opts.setting), **saved}, cfg)
        if conflicts:
            raise ValueError(f"resuming {out}: {', '.join(conflicts)} differ from the run's; a resumed run keeps them")
        model = MFGNet(cfg).to(device)
        model.load_state_dict(ckpt["model"])
        optimizer = torch.optim.Adam(model.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
        optimizer.load_state_dict(ckpt["optimizer"])
        state.update(ckpt["state"])
        # the run's start as recorded (None: a run that predates the record), then each resume's, this one's last
        made_by = ckpt.get("provenance") or {"run": None, "resumes": []}
        made_by = {"run": made_by.get("run"), "resumes": [*made_by.get("resumes", []), run_record(
            asdict(opts), data_file, at={"epoch": state["epoch"], "batch": state["batch"]})]}
        before = [r["data"] for r in (made_by["run"], *made_by["resumes"][:-1]) if r and "data" in r]
        now = made_by["resumes"][-1]["data"]
        if before and before[-1]["sha256"] != now["sha256"]:  # the data folder is this process's: said, not refused
            print(f"note: resuming on other data than the run's so far: {data_file} "
                  f"(sha256 {now['sha256'][:12]}), not {before[-1]['folder']}/{before[-1]['file']} "
                  f"(sha256 {before[-1]['sha256'][:12]}); its validation split and shapes differ", file=sys.stderr)
        print(f"resumed from {last_path} at epoch {state['epoch']} batch {state['batch']}")
    else:
        if opts.resume:
            print(f"no {last_path} to resume from: starting a new run")
        init = read_checkpoint(opts.init) if opts.init else None
        if init is None:
            cfg = MFGNetConfig.from_dict({**MFGNetConfig().to_dict(), **opts.config})
        else:  # fine-tuning continues the checkpoint's network (its config), not the defaults'
            cfg, conflicts = init_config(opts.config, init["config"])
            if conflicts:
                raise ValueError(f"training {out} from {opts.init}: {', '.join(conflicts)}: fine-tuning keeps the "
                                 "checkpoint's network; leave these out or give its values")
            opts.config = cfg.to_dict()
        model = MFGNet(cfg).to(device)
        if init is not None:
            model.load_state_dict(init["model"])
            print(f"initialised from {opts.init} (its network: {cfg.to_dict()})")
            trained_on = init.get("setting")
            if trained_on and trained_on != opts.setting:  # --setting is the run's own, not the checkpoint's
                print(f"note: {opts.init} was trained on the {trained_on!r} setting; this run trains and validates on "
                      f"{opts.setting!r} (--setting{'' if opts.recipe else ', no --recipe'}), and its export takes "
                      f"{opts.setting!r}'s protocol (reference radius, rotation search section); give --setting "
                      f"{trained_on} (and the checkpoint's --recipe) to fine-tune it on its own pairs", file=sys.stderr)
        init_file = resolve_checkpoint(opts.init).resolve() if opts.init else None
        made_by = {"run": run_record(asdict(opts), data_file, init=init_file and {
            "checkpoint": portable_path(init_file), "sha256": file_sha256(init_file),
            "provenance": init.get("provenance")}), "resumes": []}
        optimizer = torch.optim.Adam(model.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
        if run_files:  # overwrite: the run it replaces goes once the new one is ready to start
            remove_run(out, run_files)
            print(f"replacing the run in {out}: deleted its {', '.join(run_files)}")
    (out / "config.json").write_text(json.dumps({"model": cfg.to_dict(), "train": asdict(opts),
                                                 "provenance": made_by}, indent=2))

    def checkpoint(path: Path, **extra) -> None:
        state["partial"] = ({"sums": dict(sums), "seen": seen, "compute": compute, "seconds": time.time() - epoch_start}
                            if state["batch"] else None)  # inside an epoch: what its record needs of the batches done
        save_checkpoint(
            path,
            model,
            optimizer=optimizer.state_dict(),
            state=dict(state),
            protocol=asdict(protocol),
            setting=opts.setting,
            provenance=made_by,
            **extra,
        )

    begin = time.time()
    last_save = time.time()
    stopped_by, timed_out = None, False
    prefetch = device.type == "cuda" if opts.prefetch is None else opts.prefetch
    from tqdm import tqdm

    with GracefulStop() as stop:  # SIGTERM / SIGINT: finish the step, checkpoint, return
        while state["epoch"] < opts.epochs:
            epoch = state["epoch"]
            for group in optimizer.param_groups:
                group["lr"] = lr_at(opts, epoch)
            model.train()
            n_batches = stream.batches_per_epoch(opts.batch_size)
            if opts.max_batches_per_epoch:
                n_batches = min(n_batches, opts.max_batches_per_epoch)
            sums = {"keypoint": 0.0, "matching": 0.0, "credibility": 0.0, "total": 0.0}
            seen, epoch_start, compute = 0, time.time(), 0.0
            partial = state["partial"] if state["batch"] else None
            if partial:  # resumed inside this epoch: its record covers the batches before the stop too
                sums, seen, compute = dict(partial["sums"]), partial["seen"], partial["compute"]
                epoch_start -= partial["seconds"]
            bar = tqdm(total=n_batches, initial=state["batch"], desc=f"epoch {epoch}", unit="batch", mininterval=5)
            batches = epoch_batches(stream, epoch, opts.batch_size, prefetch, state["batch"], opts.workers)
            for b, batch in enumerate(batches, start=state["batch"]):  # resumed inside an epoch: from its batch
                if b >= n_batches:
                    break
                tic = time.perf_counter()
                src, tgt, R_gt, t_gt = (
                    torch.as_tensor(batch[k]).to(device) for k in ("source", "target", "rotation", "translation")
                )
                src_idx, tgt_idx = sample_training_keypoints(
                    src,
                    tgt,
                    R_gt,
                    t_gt,
                    cfg.train_positives,
                    cfg.train_negatives,
                    cfg.match_threshold,
                    batch_generator(opts.seed, epoch, b),
                )
                outputs = model(src, tgt, src_idx=src_idx, tgt_idx=tgt_idx)
                losses = registration_losses(outputs, src, tgt, R_gt, t_gt, cfg.match_threshold)
                optimizer.zero_grad(set_to_none=True)
                losses.total.backward()
                optimizer.step()
                compute += time.perf_counter() - tic
                for k in ("keypoint", "matching", "credibility", "total"):
                    sums[k] += float(getattr(losses, k).detach())
                seen += 1
                state["batch"] = b + 1
                bar.update(1)
                bar.set_postfix(
                    loss=f"{sums['total'] / seen:.3f}", ms_pair=f"{1000 * compute / seen / opts.batch_size:.0f}"
                )
                if time.time() - last_save > 60 * opts.checkpoint_minutes:
                    checkpoint(last_path)
                    last_save = time.time()
                if stop.requested or (opts.max_minutes and time.time() - begin > 60 * opts.max_minutes):
                    break
            bar.close()
            if state["batch"] < n_batches:  # stopped by a signal or by max_minutes inside an epoch
                checkpoint(last_path)
                why = f"on {stop.requested}" if stop.requested else f"after {opts.max_minutes} min"
                print(f"stopped {why} at epoch {epoch} batch {state['batch']}; --resume continues there")
                stopped_by, timed_out = stop.requested, not stop.requested
                break
            R, t, secs = predict_poses(model, val_pairs, batch_size=16)
            val = registration_metrics(R, t, val_pairs["rotation"], val_pairs["translation"], secs)
            record = {
                "epoch": epoch,
                "lr": lr_at(opts, epoch),
                "batches": seen,
                **{f"train_{k}": v / max(seen, 1) for k, v in sums.items()},
                **{f"val_{k}": v for k, v in val.items()},
                "s_per_pair": compute / max(seen * opts.batch_size, 1),
                "epoch_minutes": (time.time() - epoch_start) / 60,
                "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
            }
            with log_path.open("a") as f:
                f.write(json.dumps(record) + "\n")
            print(json.dumps(record))
            state["epoch"], state["batch"] = epoch + 1, 0
            metric = val["mae_r"]
            if not all(bool(torch.isfinite(v).all()) for v in model.state_dict().values() if v.is_floating_point()):
                # a diverged network (NaN or inf weights) still yields finite poses (NaN credibilities fall back to
                # uniform weights over arbitrary matches), so its MAE(R) must not make it the best checkpoint
                print(f"epoch {epoch}: the network's weights hold NaN or inf (training diverged; lower --lr); "
                      "not a candidate for best.pt", file=sys.stderr)
                metric = math.inf
            if metric < state["best"]:
                state["best"], state["best_epoch"], state["stale"] = metric, epoch, 0
                checkpoint(best_path, val=val)
            else:
                state["stale"] += 1
            if opts.snapshot_every and epoch % opts.snapshot_every == 0:  # weights only, chosen later elsewhere
                save_checkpoint(out / "snapshots" / f"epoch_{epoch:04d}.pt", model, state=dict(state), val=val,
                                setting=opts.setting, provenance=made_by)
            checkpoint(last_path)
            last_save = time.time()
            if state["stale"] >= opts.patience:
                print(f"validation plateaued for {opts.patience} epochs; stopping at epoch {epoch}")
                break
            if stop.requested and state["epoch"] < opts.epochs:
                print(f"stopped on {stop.requested} after epoch {epoch}; --resume continues there")
                stopped_by = stop.requested
                break
            if opts.max_minutes and time.time() - begin > 60 * opts.max_minutes:
                timed_out = state["epoch"] < opts.epochs
                break
    if state["best_epoch"] < 0:  # no epoch validated, or every validation MAE(R) NaN or inf: no best.pt written
        return TrainOutcome(None, stopped_by, state["epoch"], timed_out)
    return TrainOutcome(best_path, stopped_by, state["epoch"], timed_out)
