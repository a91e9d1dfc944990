"""What a cheaper network would cost the service: ``python -m bench.network_cost``.

For each network shape (``MFGNetConfig`` overrides; ``--shapes`` as JSON objects, default: the bundled shape and
narrower, shallower and shorter ones), an untrained network of that shape is exported to ONNX as the service runs it
(:func:`export.onnx_export.write_model_folder`, no parity check: the weights are random, the arithmetic is the
trained network's) and registers one pair of the real-scan set (``--pair``; ``DIR``, else ``$MFGNET_REAL_DATA``,
else ``../shared/data/real``) in process with the registrar's own timing of the network pass
(``timing_ms.encoder + iterations + svd``; ``refine="none"``, no search, so that random weights change no other
work). The shapes take turns ``--rounds`` times and each figure is the median, so that the machine's drift falls on
all of them.

Only the time is measured: whether a shape registers as well needs it trained (``scripts/device_train.py``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path

import numpy as np
import torch

from bench.real_scans import scan_set
from bench.report_io import emit_report, json_destination, json_object, machine_info, positive_int
from export.onnx_export import write_model_folder
from model.checkpoint import read_checkpoint, save_checkpoint
from model.config import MFGNetConfig
from model.network import MFGNet
from service.registrar import Registrar, default_threads

DEFAULT_SHAPES = ({}, {"emb_dims": 32}, {"encoder_blocks": 3}, {"emb_dims": 32, "encoder_blocks": 3},
                  {"iterations": 3}, {"iterations": 2}, {"matcher_channels": 16}, {"keypoints": 64}, {"knn": 8})
NETWORK_STAGES = ("encoder", "iterations", "svd")


def exported(shape: dict, folder: Path, seed: int = 0) -> Registrar:
    """A registrar serving an untrained network of ``shape`` (``MFGNetConfig`` overrides), exported under ``folder``."""
    torch.manual_seed(seed)
    model = MFGNet(MFGNetConfig.from_dict({**MFGNetConfig().to_dict(), **shape})).eval()
    checkpoint = folder / "untrained.pt"
    save_checkpoint(checkpoint, model)
    out = folder / "model"
    write_model_folder(out, checkpoint, model, read_checkpoint(checkpoint), "clean", "0.0.0", None)
    return Registrar(out, warmup=True)


def timed(registrar: Registrar, source: np.ndarray, target: np.ndarray) -> float:
    """Milliseconds of the network pass of one registration of the pair."""
    timing = registrar.register(source, target, refine="none", rotation_search=False).timing_ms
    return sum(timing.get(stage, 0.0) for stage in NETWORK_STAGES)


def shape_overrides(text: str) -> dict:
    """An argparse ``type`` for ``--shapes``: a JSON object of ``MFGNetConfig`` fields that makes a network config."""
    shape = json_object(text, "MFGNetConfig fields")
    fields = MFGNetConfig().to_dict()
    unknown = sorted(set(shape) - set(fields))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown MFGNetConfig field {', '.join(unknown)}")
    wrong = [key for key, value in shape.items()  # a string for a count, say (an int is a float's value too)
             if type(value) is not type(fields[key]) and not (type(fields[key]) is float and type(value) is int)]
    if wrong:
        raise argparse.ArgumentTypeError(f"{', '.join(wrong)}: not of the default's type in {text}")
    try:
        MFGNetConfig.from_dict({**fields, **shape})
    except (TypeError, ValueError) as err:
        raise argparse.ArgumentTypeError(f"{text}: {err}") from None
    return shape


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", help="real-scan set (default: $MFGNET_REAL_DATA or ../shared/data/real)")
    parser.add_argument("--pair", default="dragon_168_144", help="the pair registered (a file stem of the set)")
    parser.add_argument("--shapes", nargs="+", type=shape_overrides, default=list(DEFAULT_SHAPES),
                        help="MFGNetConfig overrides, one JSON object per shape ({} is the bundled shape)")
    parser.add_argument("--rounds", type=positive_int, default=15)
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)
    directory = scan_set(parser, args.dir, [args.pair], option="--pair")
    json_destination(args.json)
    with np.load(directory / f"{args.pair}.npz") as data:
        source, target = data["source"].astype(np.float32), data["target"].astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        registrars = [exported(shape, Path(tmp) / str(i)) for i, shape in enumerate(args.shapes)]
        times: list[list[float]] = [[] for _ in args.shapes]
        for _ in range(args.rounds):
            for registrar, rows in zip(registrars, times, strict=True):
                rows.append(timed(registrar, source, target))
    first = statistics.median(times[0])
    rows = []
    for shape, measured in zip(args.shapes, times, strict=True):
        median = statistics.median(measured)
        rows.append({"shape": shape, "network_ms": round(median, 2), "of_first": round(median / first, 2)})
        print(json.dumps(rows[-1]))
    report = {"benchmark": "network_cost", "pair": args.pair, "rounds": args.rounds,
              "machine": machine_info(default_threads()), "rows": rows}
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
