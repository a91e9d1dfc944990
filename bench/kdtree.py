"""The runtime's KD-tree (``service.kdtree``, pykdtree) against scipy's ``cKDTree``, in the same run.

``python -m bench.kdtree --pairs dense.npz [--refine icp-plane] [--count 40] [--json out.json]``

Registers each pair twice with ``Registrar.register`` (bundled ``general``), once with every runtime module's
``KDTree`` and once with a scipy-backed class of the same interface, alternating which goes first, and
reports the median of each ``timing_ms`` stage per backend and the largest rotation difference between
the two backends' poses (they should agree to float rounding).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import service.kdtree
from bench.report_io import checked, emit_report, json_destination, npz_arrays, positive_int
from model.cli_inputs import model_dir
from service.refine_modes import REFINE_MODES


class ScipyKDTree:
    """``service.kdtree.KDTree``'s interface on scipy's ``cKDTree`` (the runtime's tree before pykdtree)."""

    def __init__(self, points: np.ndarray):
        self._tree = cKDTree(np.asarray(points, dtype=np.float64))
        self.n = self._tree.n

    def query(
        self, points: np.ndarray, k: int = 1, distance_upper_bound: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        bound = np.inf if distance_upper_bound is None else distance_upper_bound
        return self._tree.query(np.asarray(points, dtype=np.float64), k=k, distance_upper_bound=bound)


def use_backend(tree_class: type) -> None:
    """Point every loaded runtime module's ``KDTree`` at ``tree_class``."""
    for name, module in list(sys.modules.items()):
        if name.startswith("service.") and name != "service.kdtree" and hasattr(module, "KDTree"):
            module.KDTree = tree_class


def run(pairs_path: Path, refine: str, count: int, model: str) -> dict:
    from service.manifest import model_folder
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    pairs = dict(np.load(pairs_path))  # read once: an NpzFile decompresses an array on every access
    backends = {"pykdtree": service.kdtree.KDTree, "scipy": ScipyKDTree}
    timings: dict[str, list[dict[str, float]]] = {name: [] for name in backends}
    rotations: dict[str, list[np.ndarray]] = {name: [] for name in backends}
    n = min(count, len(pairs["source"]))
    for i in range(n):
        order = list(backends) if i % 2 else list(backends)[::-1]
        for name in order:
            use_backend(backends[name])
            result = registrar.register(pairs["source"][i], pairs["target"][i], refine=refine)
            timings[name].append(result.timing_ms)
            rotations[name].append(result.rotation)
    use_backend(service.kdtree.KDTree)
    cos = [(np.trace(a @ b.T) - 1) / 2 for a, b in zip(rotations["pykdtree"], rotations["scipy"], strict=True)]
    return {
        "pairs": str(pairs_path), "n": n, "refine": refine, "model": model,
        "median_ms": {
            name: {stage: float(np.median([t.get(stage, 0.0) for t in rows])) for stage in rows[0]}
            for name, rows in timings.items()
        },
        "max_rotation_difference_deg": float(np.degrees(np.arccos(np.clip(min(cos), -1.0, 1.0)))),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True)
    parser.add_argument("--refine", default="icp-plane", choices=REFINE_MODES)
    parser.add_argument("--count", type=positive_int, default=40)
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    npz_arrays(parser, args.pairs)
    checked(model_dir, args.model)
    json_destination(args.json)
    report = run(args.pairs, args.refine, args.count, args.model)
    emit_report(report, args.json)


if __name__ == "__main__":
    main()
