"""How long making one training batch of a recipe's pairs takes on the CPU, per share of camera-view batches:
``python -m bench.pair_batches [--recipe general] [--views-share 0 --views-share 1] [--json out.json]``.

The pairs come from the first 3,200 ``clean`` training shapes (``model.data.TrainPairStream``); each share's stream
makes one untimed batch, then ``--batches`` timed ones; the report gives the mean ms per batch.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.report_io import checked, emit_report, json_destination, machine_info, positive_int, provenance
from model.cli_inputs import require_shapes
from model.data import TrainPairStream, load_shapes
from model.recipes import RECIPES, recipe_draw

SHAPES = 3200  # the training shapes the pairs are cut from


def share(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text}: a share of batches, 0-1")
    return value


def ms_per_batch(recipe: str, views_share: float, batch_size: int, batches: int, data: str | None) -> float:
    """The mean ms of making one batch of ``batch_size`` pairs of ``recipe`` with ``views_share``, over ``batches``
    after one untimed batch."""
    shapes, _ = load_shapes("train", "clean", data)
    stream = TrainPairStream(shapes[:SHAPES], recipe_draw(recipe, 60.0, None, views_share), 0).epoch(0, batch_size)
    next(stream)
    begin = time.perf_counter()
    for _ in range(batches):
        next(stream)
    return 1000 * (time.perf_counter() - begin) / batches


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recipe", choices=RECIPES, default="general")
    parser.add_argument("--views-share", type=share, action="append", default=None,
                        help="share of camera-view batches (repeat; default: 0 and 1)")
    parser.add_argument("--batch-size", type=positive_int, default=32)
    parser.add_argument("--batches", type=positive_int, default=15, help="timed batches per share")
    parser.add_argument("--data", default=None, help="ModelNet40 folder (default: MFGNET_DATA or ../shared)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    checked(require_shapes, "train", "clean", args.data)
    json_destination(args.json)
    shares = args.views_share or [0.0, 1.0]
    report = {"benchmark": "pair_batches", "recipe": args.recipe, "batch_size": args.batch_size,
              "batches": args.batches, "shapes": SHAPES,
              "ms_per_batch": {str(s): round(ms_per_batch(args.recipe, s, args.batch_size, args.batches, args.data), 2)
                               for s in shares},
              "machine": machine_info(1), "provenance": provenance([])}  # one Python thread makes the pairs
    emit_report(report, args.json)


if __name__ == "__main__":
    main()
