"""What kind of failure each wrong result is: ``python -m bench.failures``.

The real-scan set's cases (:func:`bench.search_network.cases`: every pair as scanned and at ``--turns`` seeded
rotations for each of ``--seeds``, in each of ``--scales``; ``--derived``: the pairs derived from the set) are
registered in process with the service's defaults. Each case the data README's thresholds call wrong is registered
again from its true pose (``initial_transform``: a candidate beside the plain network's pose, then the pipeline's own
ranking, refinement and checks; no rotation search), and the failure is put in one of three classes:

- ``truth leaves``: even from the true pose the pipeline ends outside the thresholds: the clouds pull its refinement
  away or its ranking prefers another pose (too little overlap, or surfaces that slide), so no better candidate
  would make it right;
- ``fits worse``: from the true pose it stays right but overlays no more of the working source on the target (inlier
  ratio) than the wrong result: the clouds favour the wrong pose, and a pipeline that ranks poses by their fit
  prefers it whatever its candidates;
- ``not reached``: from the true pose it stays right and fits better: no candidate reached the right basin. A network
  or search that gets closer to the truth would fix these, and only these.

It prints one row per failure (errors, inlier ratios of both poses) and the counts per class and sensor; ``--json``
writes them.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

from bench.real_scans import Case, judged, require_thresholds, scan_set
from bench.report_io import (
    checked,
    json_destination,
    machine_info,
    non_negative_int,
    positive_float,
    positive_int,
    provenance,
)
from bench.search_network import DEFAULTS, cases, registered
from model.cli_inputs import model_dir
from service.manifest import bundled_models_dir
from service.registrar import Registrar, default_threads
from service.result import RegistrationResult

CLASSES = ("truth leaves", "fits worse", "not reached")


def failure_class(truth_right: bool, truth_ratio: float, wrong_ratio: float) -> str:
    """The class of a wrong result (module docstring) from the run started at the true pose: whether it stayed
    right, its inlier ratio, and the wrong result's."""
    if not truth_right:
        return "truth leaves"
    return "fits worse" if truth_ratio <= wrong_ratio else "not reached"


def examine(registrar: Registrar, case: Case) -> dict | None:
    """``None`` where the defaults register ``case`` right; else the failure's row."""
    result, seconds = registered(registrar, case)
    returned = judged(case, result.rotation, result.translation)
    return None if returned["success"] else failure_row(registrar, case, result, returned, seconds)


def from_true_pose(registrar: Registrar, source: np.ndarray, target: np.ndarray, truth: np.ndarray
                   ) -> RegistrationResult:
    """``source`` registered onto ``target`` from its true pose ``truth [4, 4]`` (``initial_transform``: a candidate
    beside the plain network's pose) with the service's refinement and no search: where the pipeline goes from there."""
    return registrar.register(source, target, refine=DEFAULTS["refine"], rotation_search=False, initial_transform=truth)


def failure_row(registrar: Registrar, case: Case, result: RegistrationResult, returned: dict, seconds: float) -> dict:
    """The row of a wrong ``result`` of ``case`` (``returned``: its :func:`judged` errors; ``seconds``: its time),
    classed after ``registrar`` registers the case again from its true pose (module docstring)."""
    from_truth = from_true_pose(registrar, case.source, case.target, case.src_to_tgt)
    stayed = judged(case, from_truth.rotation, from_truth.translation)
    return {"case": f"{case.name}/{case.variant}/x{case.scale:g}", "sensor": case.sensor,
            "class": failure_class(stayed["success"], from_truth.inlier_ratio, result.inlier_ratio),
            "rotation_error_deg": returned["rotation_error_deg"], "translation_error": returned["translation_error"],
            "inlier_ratio": round(result.inlier_ratio, 4), "reliable": bool(result.reliable),
            "from_truth": {"rotation_error_deg": stayed["rotation_error_deg"],
                           "translation_error": stayed["translation_error"],
                           "inlier_ratio": round(from_truth.inlier_ratio, 4)},
            "seconds": round(seconds, 3)}


def run(registrar: Registrar, all_cases: list[Case]) -> dict:
    """Every case through :func:`examine`: the failures' rows and their counts per class, overall and per sensor."""
    failures = [row for row in (examine(registrar, case) for case in all_cases) if row is not None]
    by_sensor: dict[str, Counter] = {}
    for row in failures:
        by_sensor.setdefault(row["sensor"], Counter())[row["class"]] += 1
    counts = Counter(row["class"] for row in failures)
    return {"benchmark": "failures", "cases": len(all_cases), "failures": len(failures),
            "classes": {name: counts[name] for name in CLASSES},
            "by_sensor": {sensor: {name: c[name] for name in CLASSES} for sensor, c in sorted(by_sensor.items())},
            "rows": failures}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=None, help="real-scan set (default: bench.real_scans.data_dir)")
    parser.add_argument("--model-dir", type=Path, default=None, help="exported model (default: the bundled general)")
    parser.add_argument("--seeds", type=non_negative_int, nargs="+", default=[0, 1])
    parser.add_argument("--turns", type=positive_int, default=10)
    parser.add_argument("--scales", type=positive_float, nargs="+", default=[1.0])
    parser.add_argument("--pairs", nargs="+", default=None, help="only these pairs (file stems)")
    parser.add_argument("--derived", action="store_true", help="the pairs derived from the set instead of its own")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    directory = scan_set(parser, args.data, args.pairs, args.derived)
    if args.model_dir:
        checked(model_dir, args.model_dir, "--model-dir")
    json_destination(args.json)
    all_cases = cases(directory, args.seeds, args.turns, tuple(args.scales), args.pairs, args.derived)
    require_thresholds(parser, all_cases)  # judged() would refuse a sensor of no class after its first registration
    model = args.model_dir or bundled_models_dir() / "general"
    made_by = provenance([model])  # before the run: the shared checkout may move on during it
    report = {**run(Registrar(model), all_cases), "data": str(directory), "seeds": args.seeds, "turns": args.turns,
              "scales": args.scales, "pairs": args.pairs, "derived": args.derived,
              "units": "rotation errors in degrees; translation errors in the case's unit (x1: metres, x1000: "
                       "millimetres); seconds",
              "machine": machine_info(default_threads()), "provenance": made_by}
    for row in report["rows"]:
        truth = row["from_truth"]
        print(f"{row['case']:<40} {row['class']:<13} {row['rotation_error_deg']:7.2f} deg"
              f" {row['translation_error']:<8g} ratio {row['inlier_ratio']:.3f}"
              f" | from the truth {truth['rotation_error_deg']:6.2f} deg"
              f" {truth['translation_error']:<8g} ratio {truth['inlier_ratio']:.3f}")
    print(json.dumps({k: report[k] for k in ("cases", "failures", "classes", "by_sensor")}, indent=1))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return report


if __name__ == "__main__":
    main()
