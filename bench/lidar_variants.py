"""LiDAR frames metres apart, made from the real-scan set's LiDAR pair: ``python -m bench.lidar_variants [DIR]``.

The set's LiDAR pair moved 0.5 m between its frames. Each variant takes the pair's source, expressed in the target's
frame by the ground truth, as a sensor ``distance`` m away and turned ``yaw`` about the vertical would hold it, crops
it and the target to ``radius`` m about their own sensors, and registers it in process with the service's defaults
(``refine="icp-plane"``, ``rotation_search="auto"``) and with FPFH + RANSAC + ICP
(:func:`bench.real_scans.fpfh_ransac_icp`, ``--no-fpfh`` to skip): level, and again turned about its centroid by a
seeded Haar rotation. Success: the data README's LiDAR thresholds (< 5 deg, < 2 m). The points are real; the density
pattern is not a second sensor's (the source stays densest where its own sensor stood).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench.real_scans import data_dir, fpfh_ransac_icp, pose_errors, thresholds, turned
from service.manifest import bundled_models_dir
from service.registrar import Registrar

PAIR = "lidar_small_gicp"
RADII = (20.0, 30.0)  # m
DISTANCES = (5.0, 10.0, 15.0, 20.0)  # m
PER_SETTING = 3  # seeded headings and turns per (radius, distance)


def seen_from(source_in_target: np.ndarray, target: np.ndarray, distance: float, heading: float, yaw_deg: float,
              radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``source_in_target [N, 3]`` as a sensor ``distance`` m away along ``heading`` (radians) and turned ``yaw_deg``
    about the vertical would hold it, and ``target [M, 3]``, each cropped to ``radius`` m (horizontally) about its own
    sensor: float32 source, target, and the ``src_to_tgt [4, 4]`` truth."""
    sensor = distance * np.array([np.cos(heading), np.sin(heading), 0.0])  # [3] in the target's frame
    turn = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()  # [3, 3]
    near = np.linalg.norm(source_in_target[:, :2] - sensor[:2], axis=1) < radius
    source = (source_in_target[near] - sensor) @ turn  # x_target = turn @ x_source + sensor
    kept = target[np.linalg.norm(target[:, :2], axis=1) < radius]
    src_to_tgt = np.eye(4)
    src_to_tgt[:3, :3], src_to_tgt[:3, 3] = turn, sensor
    return source.astype(np.float32), kept.astype(np.float32), src_to_tgt


def load_pair(directory: Path) -> tuple[np.ndarray, np.ndarray]:
    """The LiDAR pair's source in the target's frame (float64) and its target."""
    with np.load(directory / f"{PAIR}.npz") as data:
        source, target, truth = data["source"].astype(np.float64), data["target"].astype(np.float64), data["transform"]
    return source @ truth[:3, :3].T + truth[:3, 3], target


def variants(directory: Path, seed: int = 7):
    """``(label, source, target, src_to_tgt)`` for every variant, in a seeded order."""
    rng = np.random.default_rng(seed)
    source_in_target, target = load_pair(directory)
    for radius in RADII:
        for distance in DISTANCES:
            for k in range(PER_SETTING):
                heading, yaw = rng.uniform(0, 2 * np.pi), rng.uniform(-180, 180)
                src, tgt, truth = seen_from(source_in_target, target, distance, heading, yaw, radius)
                label = f"r{radius:g}_d{distance:g}_{k}"
                yield f"{label}_level", src, tgt, truth
                src_t, truth_t = turned(src, truth, Rotation.random(random_state=rng).as_matrix())
                yield f"{label}_turned", src_t, tgt, truth_t


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", help="real-scan set (default: $MFGNET_REAL_DATA or ../shared/data/real)")
    parser.add_argument("--no-fpfh", action="store_true", help="the service only")
    parser.add_argument("--json", type=Path, help="write every row here")
    args = parser.parse_args(argv)
    registrar = Registrar(bundled_models_dir() / "general")
    max_deg, max_m = thresholds("lidar")
    rows = []
    for label, src, tgt, truth in variants(data_dir(args.dir)):
        started = time.perf_counter()
        result = registrar.register(src, tgt, refine="icp-plane", rotation_search="auto")
        seconds = time.perf_counter() - started
        degrees, metres = pose_errors(result.rotation, result.translation, truth)
        row = {"variant": label, "service_success": bool(degrees < max_deg and metres < max_m),
               "reliable": bool(result.reliable), "rotation_error_deg": round(degrees, 3),
               "translation_error_m": round(metres, 3), "service_seconds": round(seconds, 4)}
        if not args.no_fpfh:
            started = time.perf_counter()
            R, t = fpfh_ransac_icp(src, tgt)
            row["fpfh_seconds"] = round(time.perf_counter() - started, 4)
            row["fpfh_success"] = bool(np.less(pose_errors(R, t, truth), (max_deg, max_m)).all())
        rows.append(row)
        print(json.dumps(row), flush=True)
    totals = {"cases": len(rows), "service_successes": sum(r["service_success"] for r in rows),
              "reliable_given": sum(r["reliable"] for r in rows),
              "reliable_wrong": sum(r["reliable"] and not r["service_success"] for r in rows),
              "service_seconds": round(sum(r["service_seconds"] for r in rows), 2)}
    if not args.no_fpfh:
        totals |= {"fpfh_successes": sum(r["fpfh_success"] for r in rows),
                   "fpfh_seconds": round(sum(r["fpfh_seconds"] for r in rows), 2)}
    print(json.dumps(totals))
    report = {"benchmark": "lidar_variants", "totals": totals, "rows": rows}
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
