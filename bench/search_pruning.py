"""The rotation search with and without pruning, in the same run: success and search time per pairs file.

``python -m bench.search_pruning --pairs dense180.npz --pairs resampled180.npz [--json out.json]``

Registers every pair with ``rotation_search=True``, ``refine="icp-plane"`` (bundled ``general``) once per
variant -- ``full`` (every hypothesis through every iteration), ``p1k4`` / ``p1k6`` / ``p1k8`` (the default) /
``p2k4`` (all hypotheses through 1 / 1 / 1 / 2 iterations, then the best 4 / 6 / 8 / 4) -- alternating the order
pair by pair; success = recall at (5 deg, 5 cm).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.auto_trigger import pose_errors
from bench.report_io import checked, json_destination, machine_info, provenance
from model.cli_inputs import model_dir, pairs_file
from model.data import load_pairs  # reads every array once (an NpzFile re-reads per access)

# (SEARCH_PRUNE_ITERATIONS, SEARCH_KEEP) of each variant
VARIANTS = {"full": (1, 24), "p1k4": (1, 4), "p1k6": (1, 6), "p1k8": (1, 8), "p2k4": (2, 4)}


def run(pair_files: list[Path], model: str) -> dict:
    import service.rotation_search as search_module
    from service.manifest import model_folder
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    defaults = search_module.SEARCH_PRUNE_ITERATIONS, search_module.SEARCH_KEEP
    report: dict = {"model": model, "variants": VARIANTS, "files": {}}
    try:
        for path in pair_files:
            pairs = load_pairs(path)
            right: dict[str, list[bool]] = {name: [] for name in VARIANTS}
            search_ms: dict[str, list[float]] = {name: [] for name in VARIANTS}
            for i in range(len(pairs["source"])):
                for name in list(VARIANTS) if i % 2 else list(VARIANTS)[::-1]:
                    search_module.SEARCH_PRUNE_ITERATIONS, search_module.SEARCH_KEEP = VARIANTS[name]
                    result = registrar.register(pairs["source"][i], pairs["target"][i], refine="icp-plane",
                                                rotation_search=True)
                    angle, offset = pose_errors(result.rotation, result.translation, pairs["rotation"][i],
                                                pairs["translation"][i])
                    right[name].append(bool(angle < 5 and offset < 0.05))
                    search_ms[name].append(result.timing_ms["search"])
            report["files"][str(path)] = {
                name: {"n": len(right[name]), "recall_r5_t005": float(np.mean(right[name])),
                       "search_ms_median": float(np.median(search_ms[name])), "right": right[name]}
                for name in VARIANTS
            }
    finally:
        search_module.SEARCH_PRUNE_ITERATIONS, search_module.SEARCH_KEEP = defaults
    return report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, action="append", required=True)
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    for path in args.pairs:
        checked(pairs_file, path)
    checked(model_dir, args.model)
    json_destination(args.json)
    from service.registrar import default_threads  # run's Registrar

    made_by = provenance([args.model])  # before the run: the shared checkout may move on during it
    report = {**run(args.pairs, args.model), "machine": machine_info(default_threads()), "provenance": made_by}
    for path, rows in report["files"].items():
        summary = {name: (round(r["recall_r5_t005"], 3), round(r["search_ms_median"])) for name, r in rows.items()}
        print(path, summary)
    if args.json:
        args.json.write_text(json.dumps(report) + "\n")


if __name__ == "__main__":
    main()
