"""Calibration of ``rotation_search="auto"``'s trigger: which plain results should be searched.

``python -m bench.auto_trigger collect --pairs dense90.npz ... --out trigger.json`` registers every
pair twice with the bundled model and ``refine="icp-plane"``: plainly and with the rotation search on (each
result's errors, inlier ratio, residual and time; the plain one's reliability). ``auto`` returns the searched
pose when it fits better (:func:`switches`), which gives ``auto_always``: ``auto`` forced to search.
``python -m bench.auto_trigger report trigger.json --pairs ...`` then replays any trigger on those results:
the fixed inlier-ratio threshold and thresholds relative to :func:`service.quality.attainable_inlier_ratio`,
with recall at (5 deg, 5 cm), the share searched and the mean time per pair; and for the registrar's trigger
the margin by which the searched pose's inlier ratio must exceed the plain one's to replace it
(``AUTO_SWITCH_MARGINS``). Files collected before the searched pose was recorded replay the triggers only.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bench.report_io import checked
from model.cli_inputs import json_file, model_dir, output_file, pairs_file
from model.data import load_pairs  # reads every array once (an NpzFile re-reads per access)
from service.registrar import AUTO_SEARCH_RELATIVE_RATIO

FIXED = (0.7,)
RELATIVE = (0.7, 0.75, 0.8, 0.85)
AUTO_SWITCH_MARGINS = (0.0, 0.02, 0.05, 0.1, 0.15, 0.2)  # replayed with the registrar's trigger
# The fields of a collected row that report reads, and their JSON types; errors: [rotation deg, translation].
ROW_FIELDS = {"ratio": "number", "reliable": "bool", "plain": "errors", "auto_always": "errors",
              "ms_plain": "number", "ms_both": "number"}
SEARCHED_FIELDS = {"searched": "errors", "searched_ratio": "number", "rms": "number", "searched_rms": "number"}
KIND_NAMES = {"bool": "true or false", "number": "a number", "errors": "[rotation deg, translation] (two numbers)"}


def pose_errors(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray) -> tuple[float, float]:
    cos = np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(t - t_true))


def collect(pair_files: list[Path], model: str) -> dict:
    from service.manifest import model_folder
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    out = {}
    for path in pair_files:
        pairs, rows = load_pairs(path), []
        for src, tgt, R, t in zip(pairs["source"], pairs["target"], pairs["rotation"], pairs["translation"],
                                  strict=True):
            plain = registrar.register(src, tgt, refine="icp-plane")
            searched = registrar.register(src, tgt, refine="icp-plane", rotation_search=True)
            row = {
                "ratio": plain.inlier_ratio, "rms": plain.residual_rms, "reliable": plain.reliable,
                "plain": pose_errors(plain.rotation, plain.translation, R, t), "ms_plain": plain.timing_ms["total"],
                "searched": pose_errors(searched.rotation, searched.translation, R, t),
                "searched_ratio": searched.inlier_ratio, "searched_rms": searched.residual_rms,
            }
            row["auto_always"] = row["searched"] if switches(row, 0.0) else row["plain"]
            row["ms_both"] = plain.timing_ms["total"] + searched.timing_ms["total"]
            rows.append(row)
        out[path.stem] = rows
    return out


def switches(row: dict, margin: float) -> bool:
    """Whether ``auto`` returns the searched pose of a collected ``row``: its inlier ratio exceeds the plain
    one's by more than ``margin`` (0: the registrar's ``rank_hypotheses`` -- higher ratio, ties by the lower
    residual, the plain pose on a full tie)."""
    if margin > 0:
        return row["searched_ratio"] > row["ratio"] + margin
    return (row["searched_ratio"], -row["searched_rms"]) > (row["ratio"], -row["rms"])


def attainable_ratios(path: Path, reference_radius: float) -> np.ndarray:
    """:func:`attainable_inlier_ratio` of each pair's target at the quality distance (the registrar's scale)."""
    from service.normalization import Normalization
    from service.quality import attainable_inlier_ratio
    from service.registrar import INLIER_DISTANCE

    pairs = dict(np.load(path))  # source / target only (no poses needed); read once
    ratios = []
    for src, tgt in zip(pairs["source"], pairs["target"], strict=True):
        scale = Normalization.fit(src, tgt, reference_radius).scale
        ratios.append(attainable_inlier_ratio(tgt, INLIER_DISTANCE * scale))
    return np.array(ratios)


def report(results: dict, pair_files: list[Path], model: str) -> dict:
    from service.manifest import load_manifest, model_folder

    reference = float(load_manifest(model_folder(model)).normalization["reference_radius"])
    table = {}
    for path in pair_files:
        rows = results[path.stem]
        ratio = np.array([r["ratio"] for r in rows])
        reliable = np.array([r["reliable"] for r in rows])
        plain_ok = np.array([_right(r["plain"]) for r in rows])
        both_ok = np.array([_right(r["auto_always"]) for r in rows])
        ms_plain, ms_both = np.array([r["ms_plain"] for r in rows]), np.array([r["ms_both"] for r in rows])
        attainable = attainable_ratios(path, reference)
        # "or unreliable": the earlier rule also searched every unreliable result (decisions/0002)
        triggers = {f"fixed {f} or unreliable": ~reliable | (ratio < f) for f in FIXED}
        triggers |= {f"relative {a} or unreliable": ~reliable | (ratio < a * attainable) for a in RELATIVE}
        triggers |= {f"relative {a}": ratio < a * attainable for a in RELATIVE}  # the registrar's rule
        table[path.stem] = {"pairs": len(rows), "plain": float(plain_ok.mean()), "always": float(both_ok.mean()),
                            "attainable_median": float(np.median(attainable))}
        for name, searched in triggers.items():
            table[path.stem][name] = {
                "recall_r5_t005": float(np.where(searched, both_ok, plain_ok).mean()),
                "searched": float(searched.mean()),
                "ms_per_pair": float(np.where(searched, ms_both, ms_plain).mean()),
            }
        if all("searched" in r for r in rows):
            searched = triggers[f"relative {AUTO_SEARCH_RELATIVE_RATIO}"]
            for margin in AUTO_SWITCH_MARGINS:
                switched = searched & np.array([switches(r, margin) for r in rows])
                right = np.array([_right(r["searched"] if s else r["plain"])
                                  for r, s in zip(rows, switched, strict=True)])
                table[path.stem][f"relative {AUTO_SEARCH_RELATIVE_RATIO}, switch margin {margin}"] = {
                    "recall_r5_t005": float(right.mean()),
                    "switched": float(switched.mean()),
                    "right_to_wrong": int(np.sum(plain_ok & switched & ~right)),
                    "wrong_to_right": int(np.sum(~plain_ok & switched & right)),
                }
    return table


def rows_problem(rows: list, pairs: int) -> str | None:
    """What keeps ``rows`` (one file's collected results) from :func:`report`, naming the row and field: a count
    other than the file's ``pairs``, a row that is no object, a field missing or of the wrong type (a row holding
    ``searched`` needs what collect writes with it); ``None`` when they will do."""
    if len(rows) != pairs:
        return f"has {len(rows)} rows, but its pairs file holds {pairs} pairs"
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            return f"row {i}: not an object of fields"
        fields = ROW_FIELDS | (SEARCHED_FIELDS if "searched" in row else {})
        for field, kind in fields.items():
            if field not in row:
                return f"row {i}: no field {field!r}"
            if not _is(row[field], kind):
                return f"row {i}: field {field!r} is {json.dumps(row[field])[:40]}, not {KIND_NAMES[kind]}"
    return None


def _is(value: object, kind: str) -> bool:
    """Whether a JSON ``value`` is of ``kind``: ``bool``, ``number`` (not a bool) or ``errors`` (two numbers)."""
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, (list, tuple)) and len(value) == 2 and all(_is(v, "number") for v in value)


def _right(errors: Sequence[float]) -> bool:
    return errors[0] < 5 and errors[1] < 0.05


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("step", choices=("collect", "report"))
    parser.add_argument("results", type=Path, nargs="?", help="report: the collected JSON")
    parser.add_argument("--pairs", type=Path, action="append", required=True)
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--out", type=Path, default=None, help="collect: where to write the per-pair JSON")
    args = parser.parse_args(argv)
    counts = [len(checked(pairs_file, path)["source"]) for path in args.pairs]  # pairs per file
    checked(model_dir, args.model)
    if args.step == "collect":
        if args.out:
            checked(output_file, args.out, "--out")
        data = collect(args.pairs, args.model)
        text = json.dumps(data)
        if args.out:
            args.out.write_text(text)
        else:
            print(text)
        return
    if args.results is None:
        parser.error("report needs the collected JSON")
    results = checked(json_file, args.results, "results")
    missing = [path.stem for path in args.pairs] if not isinstance(results, dict) else \
        [path.stem for path in args.pairs if not isinstance(results.get(path.stem), list)]
    if missing:
        parser.error(f"results {args.results}: not what collect wrote for these --pairs "
                     f"(no rows of {', '.join(missing)})")
    for path, count in zip(args.pairs, counts, strict=True):
        problem = rows_problem(results[path.stem], count)
        if problem:
            parser.error(f"results {args.results}: {path.stem} {problem} (not what collect wrote for --pairs {path})")
    print(json.dumps(report(results, args.pairs, args.model), indent=1))


if __name__ == "__main__":
    main()
