"""Which score picks the right pose among turned starts (``service.multistart``)? The experiment behind it.

``python -m bench.local_search --pairs sparse.npz [--model general] [--angles 15,30] [--json out.json]``

For every pair: the service's pose (``Registrar.register(refine="icp-plane")``); hypotheses = that pose
turned about the target's centroid by +-a degrees about x, y and z for each angle a (plus the pose
itself), each refined by the rotation search's short point-to-point ICP (``service.icp.icp_many``); then
each ranking criterion picks one. Reports recall at (5 deg, 5 cm) of the service's pose, of an oracle
(any hypothesis right) and of each criterion's pick, and the time of the ICPs and of the scoring.
Distances are in the pairs' units (ModelNet40's unit sphere; the service scales them).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from bench.auto_trigger import pose_errors
from bench.report_io import checked, emit_report, json_destination
from model.cli_inputs import model_dir, pairs_file
from model.data import load_pairs  # reads every array once (an NpzFile re-reads per access)

ICP_DISTANCE = 0.15  # the short ICPs' correspondence cap
ICP_ITERATIONS = 20
INLIER_DISTANCES = (0.025, 0.05)
PLANE_TRUNCATIONS = (0.03, 0.05, 0.08)


def criteria_scores(src: np.ndarray, tgt: np.ndarray, R_h: np.ndarray, t_h: np.ndarray) -> dict[str, np.ndarray]:
    """Every criterion's score of each hypothesis (lower is better): ``{name: [H]}``."""
    from service.icp import target_normals
    from service.multistart import plane_distances

    tgt_tree = cKDTree(tgt)
    tgt_normals, src_normals = target_normals(tgt, tree=tgt_tree)[0], target_normals(src)[0]
    scores: dict[str, list[float]] = {}
    for R, t in zip(R_h, t_h, strict=True):
        moved = src @ R.T + t
        dist, plane = plane_distances(moved, tgt_tree, tgt, tgt_normals)
        dist_back, plane_back = plane_distances(tgt, cKDTree(moved), moved, src_normals @ R.T)
        for d in INLIER_DISTANCES:
            scores.setdefault(f"inlier_ratio_{d}", []).append(-float((dist <= d).mean()))
        for cap in PLANE_TRUNCATIONS:
            one = np.minimum(np.where(dist < 2 * cap, plane, cap), cap).mean()
            back = np.minimum(np.where(dist_back < 2 * cap, plane_back, cap), cap).mean()
            scores.setdefault(f"plane_{cap}", []).append(float(one))
            scores.setdefault(f"symmetric_plane_{cap}", []).append(float(one + back))
    return {name: np.array(values) for name, values in scores.items()}


def run(pairs_path: Path, model: str, angles: list[float]) -> dict:
    from service.icp import icp_many
    from service.manifest import model_folder
    from service.multistart import turned_poses
    from service.registrar import Registrar

    registrar = Registrar(model_folder(model))
    pairs = load_pairs(pairs_path)

    def right(R: np.ndarray, t: np.ndarray, i: int) -> bool:  # within (5 deg, 5 cm)
        angle, offset = pose_errors(R, t, pairs["rotation"][i], pairs["translation"][i])
        return angle < 5 and offset < 0.05

    hits: dict[str, int] = {"service": 0, "oracle": 0}
    icp_ms, score_ms = [], []
    for i, (src, tgt) in enumerate(zip(pairs["source"], pairs["target"], strict=True)):
        src, tgt = src.astype(np.float64), tgt.astype(np.float64)
        result = registrar.register(src, tgt, refine="icp-plane")
        R_h, t_h = turned_poses(result.rotation, result.translation, tgt.mean(0), angles)
        tic = time.perf_counter()
        R_h, t_h = icp_many(src, tgt, R_h, t_h, max_distance=ICP_DISTANCE, max_iterations=ICP_ITERATIONS)
        toc = time.perf_counter()
        scores = criteria_scores(src, tgt, R_h, t_h)
        icp_ms.append(1000 * (toc - tic))
        score_ms.append(1000 * (time.perf_counter() - toc))
        good = [right(R, t, i) for R, t in zip(R_h, t_h, strict=True)]
        service_right = right(result.rotation, result.translation, i)
        hits["service"] += service_right
        hits["oracle"] += service_right or any(good)
        for name, values in scores.items():
            hits[name] = hits.get(name, 0) + good[int(np.argmin(values))]
    n = len(pairs["source"])
    return {
        "pairs": str(pairs_path), "n": n, "model": model, "angles_deg": angles, "hypotheses": 1 + 6 * len(angles),
        "recall_r5_t005": {name: count / n for name, count in hits.items()},
        "ms_icp_median": float(np.median(icp_ms)), "ms_scores_median": float(np.median(score_ms)),
    }


def angle_list(text: str) -> list[float]:
    """An argparse ``type`` for ``--angles``: degrees, comma-separated (a ValueError is argparse's usage error)."""
    return [float(a) for a in text.split(",")]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True)
    parser.add_argument("--model", default="general", help="bundled model name or model folder")
    parser.add_argument("--angles", type=angle_list, default="15,30", help="turn angles in degrees, comma-separated")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    checked(pairs_file, args.pairs)
    checked(model_dir, args.model)
    json_destination(args.json)
    report = run(args.pairs, args.model, args.angles)
    emit_report(report, args.json)


if __name__ == "__main__":
    main()
