"""Train on a lent GPU machine: lr ``--lr-a`` (1e-4) for A minutes, then ``--lr-b`` (1e-5) for B minutes.

The ``general`` runs (``runs/general_gpu``, ``runs/general_gpu2``; docs/ACCURACY.md) were made so,
with this script's first name ``device_train_general.py``:

1. here: ``python scripts/device_train.py subset --out .gpu/data`` writes 7,000 of the 9,843 training shapes
   (seeded), small enough to travel with the working tree (``.gpu/`` is ignored by git: name ``.gpu/data`` in the
   device call's ``carry``, 64 MiB limit);
2. there (``$OUT`` is the folder that comes back): ``python3 scripts/device_train.py run --data .gpu/data --init
   runs/general/last.pt --minutes-a 6 --minutes-b 1.5`` (run 2: ``--init`` run 1's last weights, ``--minutes-a 3.5
   --minutes-b 1.2``; ``--views-share 0.3`` cuts that share of the batches as camera views, ``model.recipes``).

A model for real scans (issue 28): ``--recipe real`` (any orientation, simulated sensor pairs, checkpoints chosen on
sensor pairs: ``model.recipes``, ``model.sensor_pairs``), fine-tuning ``--init model/checkpoints/general.pt``;
``--recipe search`` for a network that only runs the rotation search (its 128 points per cloud, within 65 deg); or a
cheaper network from scratch, ``--config '{"emb_dims": 32, "encoder_blocks": 3}'`` (``model.config.MFGNetConfig``
overrides) without ``--init``, with a larger ``--lr-a``.

Several runs share one GPU with ``side-by-side`` (each makes its batches in its own ``--workers`` processes; the
machine has 16 cores): ``python3 scripts/device_train.py side-by-side --hard-seconds 500 --run "search:--recipe
search --workers 5 --data .gpu/data --init model/checkpoints/general.pt --minutes-a 5 --minutes-b 1.5
--snapshot-every 3" --run "real:--recipe real --workers 9 ..."`` leaves ``$OUT/search.tar`` and ``$OUT/real.tar``
(decision record 0044's runs; pykdtree is not on that machine: carry its wheel, as the device notes say).

Phase A writes ``$OUT/a/{best.pt, log.jsonl}``, phase B (initialised from A's last weights)
``$OUT/b/{best.pt, last.pt, log.jsonl}``, with ``--snapshot-every N`` also ``snapshots.tar`` (the weights after every
N-th epoch: simulated validation does not rank real-scan models, 0033). Both validate every 100 batches (the
``general`` recipe on the ``resampled`` setting at ``--max-angle``, default 60 degrees; ``real`` on sensor pairs over
its rotations), so their ``best.pt`` are comparable. If a phase fails with the prefetching worker it is retried once
without it, in the same folder: continuing the failed try's run from its ``last.pt``, or replacing what it left where
it wrote none (``TrainOptions.resume`` / ``overwrite``; ``train`` refuses a folder that holds a run otherwise, so a
phase folder left from an earlier run on this machine stops the script instead of being overwritten).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path


def write_subset(out: Path, shapes: int, seed: int) -> None:
    """A seeded subset of the training file (points float16, labels)."""
    import numpy as np

    from model.data import data_dir

    with np.load(data_dir(None) / "modelnet40_train.npz") as data:
        points, labels = data["points"], data["labels"]
    keep = np.sort(np.random.default_rng(seed).permutation(len(labels))[:shapes])
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "modelnet40_train.npz", points=points[keep], labels=labels[keep])
    print(f"wrote {len(keep)} of {len(labels)} training shapes to {out}")


def run_phases(args: argparse.Namespace) -> None:
    """Phase A then phase B, each stopped by time; outputs under ``$OUT``."""
    import torch

    from model.train import RunFolderInUseError, TrainOptions, train

    out = Path(os.environ.get("OUT", "/tmp/out"))
    print("torch", torch.__version__, "cuda", torch.cuda.is_available(), flush=True)
    max_angle = args.max_angle if args.max_angle is not None else (60.0 if args.recipe == "general" else None)
    common = dict(setting="resampled", recipe=args.recipe, max_angle=max_angle, epochs=100_000, lr_drop_at=1.0,
                  batch_size=args.batch_size, max_batches_per_epoch=100, val_pairs=256, checkpoint_minutes=1.0,
                  patience=100_000, device=args.device, data=args.data, views_share=args.views_share,
                  sensor_share=args.sensor_share, workers=args.workers, config=json.loads(args.config),
                  snapshot_every=args.snapshot_every)

    def phase(opts: TrainOptions) -> None:
        try:
            train(opts)
        except RunFolderInUseError:  # a run from before in the phase's folder: kept, not retried over
            raise
        except Exception:  # one retry without the worker process, in the same folder, then let it fail
            traceback.print_exc()
            print("retrying without prefetch", flush=True)
            opts.prefetch = False
            opts.resume = (Path(opts.out) / "last.pt").exists()  # the failed try's run from its last checkpoint,
            opts.overwrite = not opts.resume  # else a new run over what it left (a log, best.pt or snapshots)
            train(opts)

    def pack_snapshots(folder: Path) -> None:  # one file instead of many (at most 8 come back, 2 folders down)
        if (folder / "snapshots").is_dir():
            shutil.make_archive(str(folder / "snapshots"), "tar", folder / "snapshots")
            shutil.rmtree(folder / "snapshots")

    begin = time.time()
    phase(TrainOptions(out=str(out / "a"), init=args.init, lr=args.lr_a, max_minutes=args.minutes_a, **common))
    pack_snapshots(out / "a")
    print(f"phase a done after {(time.time() - begin) / 60:.2f} min", flush=True)
    handover = Path(tempfile.mkdtemp()) / "phase_a_last.pt"  # runs side by side each keep their own
    shutil.copy(out / "a" / "last.pt", handover)
    for name in ("last.pt", "config.json"):  # at most 8 files come back from the machine
        (out / "a" / name).unlink()
    phase(TrainOptions(out=str(out / "b"), init=str(handover), lr=args.lr_b, max_minutes=args.minutes_b, **common))
    (out / "b" / "config.json").unlink()
    pack_snapshots(out / "b")
    print(f"all done after {(time.time() - begin) / 60:.2f} min", flush=True)


def side_by_side(specs: list[str], hard_seconds: float) -> None:
    """Several ``run`` commands at once on one GPU, each killed after ``hard_seconds``; each run's folder (phases,
    snapshots, its log) is packed into ``$OUT/NAME.tar``, the only files that come back."""
    out = Path(os.environ.get("OUT", "/tmp/out"))
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp())
    runs = {}
    for spec in specs:
        name, _, args = spec.partition(":")
        folder = work / name
        folder.mkdir()
        log = (folder / "train.log").open("w")
        runs[name] = (subprocess.Popen([sys.executable, __file__, "run", *shlex.split(args)], stdout=log,
                                       stderr=subprocess.STDOUT, env={**os.environ, "OUT": str(folder)}), log)
    deadline = time.time() + hard_seconds
    for name, (process, log) in runs.items():
        try:
            process.wait(timeout=max(deadline - time.time(), 0))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()
        shutil.make_archive(str(out / name), "tar", work / name)
        print(f"{name}: exit {process.returncode}, packed into {out / name}.tar", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    subset = sub.add_parser("subset", help="write a seeded subset of the training shapes")
    subset.add_argument("--out", type=Path, required=True)
    subset.add_argument("--shapes", type=int, default=7000)
    subset.add_argument("--seed", type=int, default=0)
    run = sub.add_parser("run", help="train phase A then phase B")
    run.add_argument("--data", required=True, help="folder holding modelnet40_train.npz")
    run.add_argument("--init", help="initial weights (default: a new network of --config)")
    run.add_argument("--recipe", choices=("general", "real", "search"), default="general")
    run.add_argument("--config", default="{}", help="MFGNetConfig overrides as JSON (a new network's shape)")
    run.add_argument("--max-angle", type=float,
                     help="rotation range (default: 60 for general, else the recipe's own: real 180, search 65)")
    run.add_argument("--sensor-share", type=float, help="with --recipe real or search: share of sensor batches")
    run.add_argument("--lr-a", type=float, default=1e-4)
    run.add_argument("--lr-b", type=float, default=1e-5)
    run.add_argument("--minutes-a", type=float, required=True)
    run.add_argument("--minutes-b", type=float, required=True)
    run.add_argument("--device", default="auto")
    run.add_argument("--batch-size", type=int, default=32)
    run.add_argument("--views-share", type=float, default=None, help="share of batches cut as camera views")
    run.add_argument("--workers", type=int, default=4, help="processes making batches ahead of the GPU")
    run.add_argument("--snapshot-every", type=int, default=0,
                     help="keep the weights after every N epochs (snapshots.tar per phase), to choose on real scans")
    sides = sub.add_parser("side-by-side", help="several runs at once, each packed into $OUT/NAME.tar")
    sides.add_argument("--run", action="append", required=True, metavar="NAME:ARGS",
                       help="a run's name and its 'run' arguments, e.g. 'search:--recipe search --workers 4 ...'")
    sides.add_argument("--hard-seconds", type=float, required=True,
                       help="kill what still runs after this long, then pack (inside the device call's limit)")
    args = parser.parse_args()
    if args.command == "subset":
        write_subset(args.out, args.shapes, args.seed)
    elif args.command == "side-by-side":
        side_by_side(args.run, args.hard_seconds)
    else:
        run_phases(args)


if __name__ == "__main__":
    main()
