"""What each set of ``Registrar.register`` options costs and buys, on the same pairs, alternating per pair.

``python -m bench.settings --pairs dense.npz --setting '{}' --setting '{"keypoints": 64, "iterations": 1}'
[--count 170] [--model general] [--json out.json]``

Each ``--setting`` is a JSON object of ``register`` keyword options (``refine`` defaults to ``icp-plane``, the
service's default). Every pair is registered once with each setting in turn, so a drift of this shared VM's speed
reaches every setting alike. The report gives per setting the isotropic rotation error (mean, median), the recall
at (1 deg, 1 cm) and (5 deg, 5 cm), the median wall time per pair and the median of each ``timing_ms`` stage.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.report_io import checked, emit_report, json_destination, json_object, machine_info, positive_int
from model.cli_inputs import model_dir, pairs_file
from model.data import load_pairs
from model.metrics import registration_metrics

DEFAULTS = {"refine": "icp-plane"}
REPORTED = ("iso_r_mean", "iso_r_median", "recall_r1_t001", "recall_r5_t005")  # of registration_metrics


def parse_setting(text: str) -> dict:
    """``--setting`` as register options: a JSON object (``{}`` = the defaults)."""
    options = json_object(text, "register options")
    from service.errors import InputError
    from service.registrar import RegistrationOptions

    unknown = sorted(set(options) - RegistrationOptions.names())
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown register option {', '.join(unknown)} (options: "
                                         f"{', '.join(sorted(RegistrationOptions.names()))})")
    try:
        RegistrationOptions.of(**{**DEFAULTS, **options})
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return options


def run(pairs_path: Path, settings: list[dict], count: int | None, model: str) -> dict:
    from service.manifest import model_folder
    from service.registrar import Registrar, default_threads

    registrar = Registrar(model_folder(model))
    pairs = load_pairs(pairs_path)
    n = len(pairs["source"]) if count is None else min(count, len(pairs["source"]))
    options = [{**DEFAULTS, **setting} for setting in settings]
    poses = [([], []) for _ in options]  # per setting: rotations [n][3, 3], translations [n][3]
    wall = [[] for _ in options]  # per setting: ms per pair
    stages: list[dict[str, list[float]]] = [{} for _ in options]
    for i in range(n):
        for s, kwargs in enumerate(options):
            begin = time.perf_counter()
            result = registrar.register(pairs["source"][i], pairs["target"][i], **kwargs)
            wall[s].append(1000 * (time.perf_counter() - begin))
            poses[s][0].append(result.rotation)
            poses[s][1].append(result.translation)
            for stage, ms in result.timing_ms.items():
                stages[s].setdefault(stage, []).append(ms)
    rows = []
    for s, kwargs in enumerate(options):
        metrics = registration_metrics(np.stack(poses[s][0]), np.stack(poses[s][1]),
                                       pairs["rotation"][:n], pairs["translation"][:n])
        rows.append({
            "options": kwargs, **{key: metrics[key] for key in REPORTED},
            "ms_per_pair_median": float(np.median(wall[s])),
            "stage_ms_median": {stage: float(np.median(v)) for stage, v in stages[s].items()},
        })
    return {"pairs": str(pairs_path), "n": n, "model": model, "machine": machine_info(default_threads()),
            "settings": rows}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True)
    parser.add_argument("--setting", type=parse_setting, action="append", required=True,
                        help="register options as a JSON object (repeat; '{}' = the defaults)")
    parser.add_argument("--count", type=positive_int, default=None, help="first COUNT pairs (default: all)")
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    checked(pairs_file, args.pairs)
    checked(model_dir, args.model)
    json_destination(args.json)
    emit_report(run(args.pairs, args.setting, args.count, args.model), args.json)


if __name__ == "__main__":
    main()
