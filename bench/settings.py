"""What each set of ``Registrar.register`` options costs and buys, on the same pairs, alternating per pair.

``python -m bench.settings --pairs dense.npz --setting '{}' --setting '{"keypoints": 64, "iterations": 1}'
[--count 170] [--model general] [--json out.json]``

``python -m bench.settings --scans [DIR] --setting ...``: the real-scan set's cases instead (``bench.real_scans``:
every pair as scanned and turned by one seeded rotation, in metres; ``DIR`` as there, default ``$MFGNET_REAL_DATA``).

Each ``--setting`` is a JSON object of ``register`` keyword options (``refine`` defaults to ``icp-plane``, the
service's default). Every pair is registered once with each setting in turn, so a drift of this shared VM's speed
reaches every setting alike. The report gives per setting the isotropic rotation error (mean, median), the recall
at (1 deg, 1 cm) and (5 deg, 5 cm) (real scans: the successes by the data README's thresholds), the median wall time
per pair (real scans: also per sensor) and the median of each ``timing_ms`` stage.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.report_io import (
    checked,
    emit_report,
    json_destination,
    json_object,
    machine_info,
    positive_int,
    provenance,
)
from model.cli_inputs import model_dir, pairs_file
from model.data import load_pairs
from model.metrics import registration_metrics

DEFAULTS = {"refine": "icp-plane"}
REPORTED = ("iso_r_mean", "iso_r_median", "recall_r1_t001", "recall_r5_t005")  # of registration_metrics
SCAN_SEED, SCAN_TURNS, SCAN_SCALES = 0, 1, (1.0,)  # --scans: the set's one-turn cases (bench.real_scans), in metres


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


def registered_in_turn(model: str, clouds: list[tuple[np.ndarray, np.ndarray]], options: list[dict]) -> tuple:
    """Every pair of ``clouds`` (source [N, 3], target [M, 3]) registered with each of ``options`` in turn: per
    option its results, its wall ms per pair and its ``timing_ms`` stages' ms per pair."""
    from service.manifest import model_folder
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    results = [[] for _ in options]  # per setting: RegistrationResult per pair
    wall = [[] for _ in options]  # per setting: ms per pair
    stages: list[dict[str, list[float]]] = [{} for _ in options]
    for source, target in clouds:
        for s, kwargs in enumerate(options):
            begin = time.perf_counter()
            result = registrar.register(source, target, **kwargs)
            wall[s].append(1000 * (time.perf_counter() - begin))
            results[s].append(result)
            for stage, ms in result.timing_ms.items():
                stages[s].setdefault(stage, []).append(ms)
    return results, wall, stages


def timing_row(wall: list[float], stages: dict[str, list[float]]) -> dict:
    """The median wall ms per pair and the median of each stage."""
    return {"ms_per_pair_median": float(np.median(wall)),
            "stage_ms_median": {stage: float(np.median(v)) for stage, v in stages.items()}}


def run(pairs_path: Path, settings: list[dict], count: int | None, model: str) -> dict:
    from service.registrar import default_threads

    pairs = load_pairs(pairs_path)
    n = len(pairs["source"]) if count is None else min(count, len(pairs["source"]))
    options = [{**DEFAULTS, **setting} for setting in settings]
    results, wall, stages = registered_in_turn(model, [(pairs["source"][i], pairs["target"][i]) for i in range(n)],
                                               options)
    rows = []
    for s, kwargs in enumerate(options):
        metrics = registration_metrics(np.stack([r.rotation for r in results[s]]),
                                       np.stack([r.translation for r in results[s]]),
                                       pairs["rotation"][:n], pairs["translation"][:n])
        rows.append({"options": kwargs, **{key: metrics[key] for key in REPORTED}, **timing_row(wall[s], stages[s])})
    return {"pairs": str(pairs_path), "n": n, "model": model, "machine": machine_info(default_threads()),
            "provenance": provenance([model]), "settings": rows}


def run_scans(directory: Path, cases: list, settings: list[dict], model: str) -> dict:
    """:func:`run` on real-scan ``cases`` of ``directory`` (:class:`bench.real_scans.Case`): successes instead of
    recall."""
    from bench.real_scans import judged
    from service.registrar import default_threads

    options = [{**DEFAULTS, **setting} for setting in settings]
    results, wall, stages = registered_in_turn(model, [(c.source, c.target) for c in cases], options)
    sensors = sorted({c.sensor for c in cases})
    rows = []
    for s, kwargs in enumerate(options):
        right = [judged(c, r.rotation, r.translation)["success"] for c, r in zip(cases, results[s], strict=True)]
        by_sensor = {sensor: float(np.median([ms for c, ms in zip(cases, wall[s], strict=True) if c.sensor == sensor]))
                     for sensor in sensors}
        rows.append({"options": kwargs, "successes": int(sum(right)), **timing_row(wall[s], stages[s]),
                     "ms_per_pair_median_by_sensor": by_sensor})
    return {"scans": str(directory), "seed": SCAN_SEED, "turns": SCAN_TURNS, "scales": list(SCAN_SCALES),
            "n": len(cases), "cases": [f"{c.name}/{c.variant}" for c in cases], "model": model,
            "machine": machine_info(default_threads()), "provenance": provenance([model]), "settings": rows}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    data = parser.add_mutually_exclusive_group(required=True)
    data.add_argument("--pairs", type=Path)
    data.add_argument("--scans", nargs="?", const="", metavar="DIR",
                      help="the real-scan set's cases, as scanned and turned once, in metres (DIR: default "
                           "$MFGNET_REAL_DATA or ../shared/data/real)")
    parser.add_argument("--setting", type=parse_setting, action="append", required=True,
                        help="register options as a JSON object (repeat; '{}' = the defaults)")
    parser.add_argument("--count", type=positive_int, default=None, help="first COUNT pairs (default: all)")
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.scans is not None:
        from bench.real_scans import load_cases, require_thresholds, scan_set

        directory = scan_set(parser, args.scans or None)
        cases = load_cases(directory, SCAN_SEED, SCAN_SCALES, turns=SCAN_TURNS)[:args.count]
        require_thresholds(parser, cases)
    else:
        checked(pairs_file, args.pairs)
    checked(model_dir, args.model)
    json_destination(args.json)
    report = run_scans(directory, cases, args.setting, args.model) if args.scans is not None \
        else run(args.pairs, args.setting, args.count, args.model)
    emit_report(report, args.json)


if __name__ == "__main__":
    main()
