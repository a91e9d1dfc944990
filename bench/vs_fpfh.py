"""The service's default registration against Open3D FPFH + RANSAC + ICP, in alternating passes.

``python -m bench.vs_fpfh --pairs dense.npz [--count 30] [--rounds 4] [--rotation-search auto]
[--json out.json]``

``mfgnet bench`` times each method in one pass over the pairs, one method after the other, so a drift
of this shared VM's speed between the passes enters their ratio. Here each round times one pass of
each method over the same pairs, back to back (each method's steady state, as a caller running only
that method sees it), alternating which goes first; each pass starts with one untimed call, so
neither pays for the other's threads still spinning or for Open3D's import. The report gives, per
method, the median over rounds of the mean ms per pair, the per-round time ratios, and the recall at
(5 deg, 5 cm) and (1 deg, 1 cm) of the last round. Needs the ``bench`` extra (Open3D).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.baselines import fpfh_ransac_icp, refuse_without_open3d
from bench.report_io import checked, emit_report, json_destination, positive_int
from model.cli_inputs import model_dir, pairs_file
from model.data import load_pairs  # reads every array once (an NpzFile re-reads per access)
from model.metrics import registration_metrics
from service.refine_modes import REFINE_MODES


def run(pairs_path: Path, count: int, rounds: int, refine: str, model: str, rotation_search: str = "off") -> dict:
    from service.manifest import model_folder
    from service.registrar import Registrar
    from service.search_mode import rotation_search_from_options

    search = rotation_search_from_options(None, rotation_search)

    registrar = Registrar(model_folder(model))
    pairs = load_pairs(pairs_path)
    n = min(count, len(pairs["source"]))

    def mfgnet(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        result = registrar.register(src, tgt, refine=refine, rotation_search=search)
        return result.rotation, result.translation

    methods = {"mfgnet": mfgnet, "fpfh_ransac_icp": fpfh_ransac_icp}
    pass_ms: dict[str, list[float]] = {name: [] for name in methods}  # mean ms per pair of each pass
    poses: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for r in range(rounds):
        for name in list(methods) if r % 2 else list(methods)[::-1]:
            method = methods[name]
            method(pairs["source"][n - 1], pairs["target"][n - 1])  # untimed
            begin = time.perf_counter()
            poses[name] = [method(pairs["source"][i], pairs["target"][i]) for i in range(n)]
            pass_ms[name].append(1000 * (time.perf_counter() - begin) / n)
    report: dict = {"pairs": str(pairs_path), "n": n, "rounds": rounds, "refine": refine, "model": model,
                    "rotation_search": rotation_search, "methods": {}}
    for name in methods:
        R = np.stack([p[0] for p in poses[name]])  # [n, 3, 3]
        t = np.stack([p[1] for p in poses[name]])  # [n, 3]
        metrics = registration_metrics(R, t, pairs["rotation"][:n], pairs["translation"][:n])
        report["methods"][name] = {
            "ms_per_pair": float(np.median(pass_ms[name])), "pass_ms_per_pair": pass_ms[name],
            "recall_r5_t005": metrics["recall_r5_t005"], "recall_r1_t001": metrics["recall_r1_t001"],
            "mae_r": metrics["mae_r"],
        }
    ratios = np.asarray(pass_ms["fpfh_ransac_icp"]) / np.asarray(pass_ms["mfgnet"])  # [rounds]
    report["fpfh_over_mfgnet"] = {"per_round": ratios.tolist(), "median": float(np.median(ratios))}
    return report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True)
    parser.add_argument("--count", type=positive_int, default=30)
    parser.add_argument("--rounds", type=positive_int, default=4)
    parser.add_argument("--refine", default="icp-plane", choices=REFINE_MODES)
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--rotation-search", choices=["off", "auto", "on"], default="off")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    checked(pairs_file, args.pairs)
    checked(model_dir, args.model)
    json_destination(args.json)
    refuse_without_open3d(parser, instead=None)
    emit_report(run(args.pairs, args.count, args.rounds, args.refine, args.model, args.rotation_search), args.json)


if __name__ == "__main__":
    main()
