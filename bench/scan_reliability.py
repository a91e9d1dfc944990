"""``reliable`` on shapes the real-scan set does not hold: ``python -m bench.scan_reliability`` (row H of
``docs/REAL_SCANS.md``).

Simulated range scans of ModelNet40 test shapes (the ``scans`` setting: two camera views of one shape, turned up to
180 deg about each axis), ``--count`` shapes for each of ``--seeds``, registered in process by ``--model`` with the
service's defaults (``refine="icp-plane"``, ``rotation_search="auto"``; :func:`bench.runtime_eval.runtime_poses`).
Right = within (5 deg, 5 cm). It prints and writes (``--json``) the pooled successes, ``reliable`` results given and
wrong, their precision (the share of them that are right) and coverage (the share of the successes given it), the same
per class, and every wrong ``reliable`` result with its kind: ``half turn`` (more than 170 deg off), ``turned``
(5-170 deg off) or ``slid`` (the rotation within 5 deg, the translation 5 cm or more off), and its failure class as
``bench.failures`` classes a real scan's: registered again from its true pose (``initial_transform``, no search), it
``truth leaves`` (ends wrong), ``fits worse`` (stays right, with an inlier ratio no higher than the wrong result's:
the fit itself prefers the wrong pose, so no check that compares fits can withhold ``reliable``) or ``not reached``
(stays right and fits better: a turn or search that reached it would flag or replace the wrong pose).
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bench.failures import CLASSES, failure_class, from_true_pose
from bench.report_io import (
    checked,
    json_destination,
    machine_info,
    non_negative_int,
    positive_int,
    provenance,
    reliable_totals,
)
from bench.runtime_eval import runtime_poses
from model.cli_inputs import model_dir, require_shapes
from model.data import class_names, make_test_pairs, protocol_for
from model.metrics import RECALL_THRESHOLDS, isotropic_errors, recall_hits

if TYPE_CHECKING:
    from service.registrar import Registrar

RIGHT = "recall_r5_t005"  # right: within (5 deg, 5 cm)
MAX_DEGREES = RECALL_THRESHOLDS[RIGHT][0]
HALF_TURN_DEGREES = 170.0  # a wrong result further off than this is a half turn
SEEDS = (5, 11, 12, 13, 14, 15)


def seed_rows(model: str, seed: int, count: int, data: str | None = None) -> list[dict]:
    """One row per pair of ``count`` seeded simulated scans at any orientation: class, errors, success, ``reliable``,
    inlier ratio; a wrong ``reliable`` result's row also its :func:`from_truth` run and failure class."""
    pairs = make_test_pairs("scans", count=count, seed=seed, path=data, protocol=protocol_for("scans", max_angle=180))
    run = runtime_poses(model, pairs, refine="icp-plane", rotation_search="auto", progress=False)
    degrees, errors = isotropic_errors(run.rotation, run.translation, pairs["rotation"], pairs["translation"])  # [M]
    right = recall_hits(degrees, errors)[RIGHT]  # [M]
    rows = [{"seed": seed, "pair": i, "label": int(pairs["label"][i]), "rotation_error_deg": round(float(d), 3),
             "translation_error": round(float(e), 4), "success": bool(right[i]), "reliable": bool(run.reliable[i]),
             "inlier_ratio": round(float(run.inlier_ratio[i]), 4)}
            for i, (d, e) in enumerate(zip(degrees, errors, strict=True))]
    wrong = [row for row in rows if row["reliable"] and not row["success"]]
    if wrong:
        from service.manifest import model_folder
        from service.registrar import Registrar

        registrar = Registrar(model_folder(model))
        for row in wrong:
            row.update(from_truth(registrar, pairs, row))
    return rows


def from_truth(registrar: Registrar, pairs: dict, row: dict) -> dict:
    """The wrong result ``row`` of ``pairs`` registered again from its true pose
    (:func:`bench.failures.from_true_pose`): its errors and inlier ratio, and its failure class
    (:func:`bench.failures.failure_class`)."""
    i = row["pair"]
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = pairs["rotation"][i], pairs["translation"][i]
    res = from_true_pose(registrar, pairs["source"][i], pairs["target"][i], truth)
    degrees, errors = isotropic_errors(res.rotation[None], res.translation[None], pairs["rotation"][i : i + 1],
                                       pairs["translation"][i : i + 1])  # [1]
    stayed = bool(recall_hits(degrees, errors)[RIGHT][0])
    return {"failure": failure_class(stayed, res.inlier_ratio, row["inlier_ratio"]),
            "from_truth": {"rotation_error_deg": round(float(degrees[0]), 3),
                           "translation_error": round(float(errors[0]), 4),
                           "inlier_ratio": round(float(res.inlier_ratio), 4)}}


def kind(row: dict) -> str:
    """How a wrong result is wrong: ``half turn``, ``turned`` or ``slid``."""
    if row["rotation_error_deg"] > HALF_TURN_DEGREES:
        return "half turn"
    return "turned" if row["rotation_error_deg"] >= MAX_DEGREES else "slid"


def report(rows: list[dict], names: list[str] | None) -> dict:
    """The pooled totals (:func:`bench.report_io.reliable_totals`), those of each class, the wrong ``reliable``
    results' count per failure class (:func:`from_truth`), and every wrong ``reliable`` result with its :func:`kind`."""
    def name(label: int) -> str:
        return names[label] if names and label < len(names) else str(label)

    by_class = {name(label): reliable_totals([r for r in rows if r["label"] == label])
                for label in sorted({r["label"] for r in rows})}
    wrong = [{**r, "class": name(r["label"]), "kind": kind(r)} for r in rows if r["reliable"] and not r["success"]]
    failures = Counter(r.get("failure") for r in wrong)
    return {"benchmark": "scan_reliability", "totals": reliable_totals(rows), "by_class": by_class,
            "reliable_wrong_by_failure": {failure: failures[failure] for failure in CLASSES},
            "reliable_wrong": wrong, "rows": rows}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--seeds", type=non_negative_int, nargs="+", default=list(SEEDS))
    parser.add_argument("--count", type=positive_int, default=170, help="pairs per seed")
    parser.add_argument("--data", default=None, help="ModelNet40 directory (default: $MFGNET_DATA, then ../shared)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    checked(model_dir, args.model)
    checked(require_shapes, "test", "scans", args.data)
    json_destination(args.json)
    from service.registrar import default_threads  # the runtime's (bench.runtime_eval)

    made_by = provenance([args.model])  # before the run: the shared checkout may move on during it
    rows: list[dict] = []
    for seed in args.seeds:
        rows += seed_rows(args.model, seed, args.count, args.data)
        print(f"seed {seed}", json.dumps(reliable_totals([r for r in rows if r["seed"] == seed])), flush=True)
    out = {**report(rows, class_names(args.data)), "seeds": args.seeds, "count": args.count,
           "units": "rotation errors in degrees; translation errors in the shapes' unit (ModelNet40: about the unit "
                    "sphere)",
           "machine": machine_info(default_threads()), "provenance": made_by}
    print("all", json.dumps(out["totals"]))
    for name, figures in out["by_class"].items():
        print(f"  {name}", json.dumps(figures))
    print("wrong reliable by failure class", json.dumps(out["reliable_wrong_by_failure"]))
    for row in out["reliable_wrong"]:
        print("  wrong reliable:", json.dumps({k: row[k] for k in ("seed", "pair", "class", "rotation_error_deg",
                                                                   "translation_error", "kind", "inlier_ratio",
                                                                   "failure")}))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
