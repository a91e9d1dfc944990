"""Choose among checkpoints by what the service returns, not by the network's validation alone.

Each checkpoint is exported to ONNX in a scratch folder (graphs and manifest; no parity check: ``mfgnet export``
runs it when the chosen one is bundled) and every pairs file is registered through ``Registrar.register`` with
the given refinement, as ``mfgnet evaluate --model`` does::

    python -m bench.select --checkpoint model/checkpoints/general.pt --checkpoint runs/general_views/best.pt \\
        --pairs scans_s7.npz --pairs dense_s7.npz --refine icp-plane --json select.json

Use selection pairs made with a seed other than the reported test pairs' (``mfgnet make-pairs ... --seed 7``).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from bench.report_io import checked, json_destination
from model.cli_inputs import checkpoint_model, pairs_file

COLUMNS = ("recall_r5_t005", "recall_r1_t001", "mae_r", "iso_r_median", "reliable_wrong_share")


def export_for_selection(checkpoint: str, out: Path) -> Path:
    """Graphs and manifest of ``checkpoint`` (path or bundled name) in ``out`` (a model folder)."""
    from export.onnx_export import write_model_folder
    from model.checkpoint import load_model, read_checkpoint, resolve_checkpoint

    path = resolve_checkpoint(checkpoint)
    data = read_checkpoint(path)
    write_model_folder(out, path, load_model(path), data, data.get("setting", "clean"), "selection", {})
    return out


def select(checkpoints: list[str], pairs_files: list[Path], refine: str) -> list[dict]:
    """One row per (checkpoint, pairs file): the metrics of ``mfgnet evaluate --model`` on the exported graphs."""
    from bench.runtime_eval import runtime_poses
    from model.data import load_pairs
    from model.metrics import registration_metrics, reliability_metrics

    pairs = {path: load_pairs(path) for path in pairs_files}
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for i, checkpoint in enumerate(checkpoints):
            folder = export_for_selection(checkpoint, Path(scratch) / f"candidate_{i}")
            for path, data in pairs.items():
                run = runtime_poses(folder, data, refine=refine, progress=False)
                R, t = run.rotation, run.translation
                metrics = registration_metrics(R, t, data["rotation"], data["translation"], run.seconds)
                metrics.update(reliability_metrics(R, t, data["rotation"], data["translation"], run.reliable))
                rows.append({"checkpoint": checkpoint, "pairs": str(path), "refine": refine, **metrics})
                print(table_line(rows[-1]), flush=True)
    return rows


def table_line(row: dict) -> str:
    return " | ".join([row["checkpoint"], Path(row["pairs"]).name, *(f"{row[c]:.3f}" for c in COLUMNS)])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", action="append", required=True, help="path or bundled name (repeat)")
    parser.add_argument("--pairs", action="append", required=True, type=Path, help="pairs .npz (repeat)")
    parser.add_argument("--refine", default="icp-plane", help="none, icp, icp-plane or icp-plane-multistart")
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)
    from service.refine_modes import REFINE_MODES

    if args.refine not in REFINE_MODES:
        parser.error(f"unknown --refine {args.refine!r}; expected one of {', '.join(REFINE_MODES)}")
    for checkpoint in args.checkpoint:
        checked(checkpoint_model, checkpoint)  # weights that fit their config: a usage error, not a traceback
    for path in args.pairs:
        checked(pairs_file, path)
    json_destination(args.json)
    print(" | ".join(["checkpoint", "pairs", *COLUMNS]))
    rows = select(args.checkpoint, args.pairs, args.refine)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
