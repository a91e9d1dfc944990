"""How far each network iteration still turns the pose, on a pairs file: the angle between the poses after
iterations ``i - 1`` and ``i`` of one registration (``return_iterations``; no refinement, no search).

``python -m bench.iteration_steps --pairs dense.npz [--count N] [--iterations 4] [--model general] [--json out.json]``

Per iteration the report gives the median and 90th percentile of that step in degrees (from the second iteration)
and the median rotation error against the pairs' truth after it: an early exit is worth something only where the
steps of the late iterations are far below the error they leave.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.report_io import checked, emit_report, json_destination, machine_info, positive_int, provenance
from model.cli_inputs import model_dir, pairs_file
from model.data import load_pairs
from model.metrics import rotation_angle_deg

MAX_ITERATIONS = 8  # the service's limit (service.options.check_iterations)


def iteration_rotations(model: str, clouds: list[tuple[np.ndarray, np.ndarray]], iterations: int) -> np.ndarray:
    """``[P, I, 3, 3]``: each pair's src_to_tgt rotation after each of ``iterations`` network iterations."""
    from service.manifest import model_folder
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    rotations = []
    for source, target in clouds:
        result = registrar.register(source, target, iterations=iterations, refine="none", rotation_search=False,
                                    return_iterations=True)
        rotations.append([pose.rotation for pose in result.iteration_poses])
    return np.asarray(rotations, dtype=np.float64)


def step_rows(rotations: np.ndarray, truth: np.ndarray) -> list[dict]:
    """Per iteration of ``rotations [P, I, 3, 3]``: the median rotation error against ``truth [P, 3, 3]`` and, from
    the second on, the median and 90th percentile of the angle to the iteration before (degrees)."""
    rows = []
    for i in range(rotations.shape[1]):
        row = {"iteration": i + 1,
               "rotation_error_deg_median": float(np.median(rotation_angle_deg(rotations[:, i], truth)))}
        if i:
            step = rotation_angle_deg(rotations[:, i], rotations[:, i - 1])  # [P]
            row |= {"step_deg_median": float(np.median(step)), "step_deg_p90": float(np.percentile(step, 90))}
        rows.append(row)
    return rows


def run(pairs_path: Path, count: int | None, iterations: int, model: str) -> dict:
    from service.registrar import default_threads

    pairs = load_pairs(pairs_path)
    n = len(pairs["source"]) if count is None else min(count, len(pairs["source"]))
    rotations = iteration_rotations(model, [(pairs["source"][i], pairs["target"][i]) for i in range(n)], iterations)
    return {"pairs": str(pairs_path), "n": n, "model": model, "iterations": iterations,
            "machine": machine_info(default_threads()), "provenance": provenance([model]),
            "per_iteration": step_rows(rotations, np.asarray(pairs["rotation"][:n], dtype=np.float64))}


def iteration_count(text: str) -> int:
    value = positive_int(text)
    if value > MAX_ITERATIONS:
        raise argparse.ArgumentTypeError(f"at most {MAX_ITERATIONS} iterations")
    return value


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True)
    parser.add_argument("--count", type=positive_int, default=None, help="first COUNT pairs (default: all)")
    parser.add_argument("--iterations", type=iteration_count, default=4, help="network iterations (default: 4)")
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    checked(pairs_file, args.pairs)
    checked(model_dir, args.model)
    json_destination(args.json)
    emit_report(run(args.pairs, args.count, args.iterations, args.model), args.json)


if __name__ == "__main__":
    main()
