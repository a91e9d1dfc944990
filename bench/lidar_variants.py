"""LiDAR frames metres apart, made from the real-scan set's LiDAR pair: ``python -m bench.lidar_variants [DIR]``.

The set's LiDAR pair moved 0.5 m between its frames. Each variant takes the pair's source, expressed in the target's
frame by the ground truth, as a sensor ``distance`` m away and turned ``yaw`` about the vertical would hold it, crops
it and the target to ``radius`` m about their own sensors, and registers it in process with the service's defaults
(``refine="icp-plane"``, ``rotation_search="auto"``) and with FPFH + RANSAC + ICP
(:func:`bench.real_scans.fpfh_ransac_icp`, ``--no-fpfh`` to skip): level, and again turned about its centroid by a
seeded Haar rotation. Success: the data README's LiDAR thresholds (< 5 deg, < 2 m). The points are real; the density
pattern is not a second sensor's (the source stays densest where its own sensor stood).

``--odometry DEG METRES`` sends every request an ``initial_transform`` as odometry would give it: the truth after
the source is turned ``DEG`` about a seeded axis through its sensor (its frame's origin) and moved ``METRES`` in a
seeded direction.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench.baselines import refuse_fpfh_without_open3d
from bench.real_scans import scan_set, turned
from bench.report_io import json_destination, provenance
from bench.variant_runs import registered, report
from service.manifest import bundled_models_dir

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


def variants(directory: Path, seed: int = 7) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
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


def odometry_guesses(degrees: float, metres: float, seed: int = 11) -> Callable[[np.ndarray], np.ndarray]:
    """``truth [4, 4] -> guess [4, 4]``: the truth composed after a turn of ``degrees`` about a seeded axis through
    the origin of the source's frame and a move of ``metres`` in a seeded direction, a new axis and direction per
    call (the same sequence for the same seed)."""
    rng = np.random.default_rng(seed)

    def guess(truth: np.ndarray) -> np.ndarray:
        axis, direction = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
        off = np.eye(4)
        off[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix()
        off[:3, 3] = metres * direction
        return truth @ off

    return guess


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", help="real-scan set (default: $MFGNET_REAL_DATA or ../shared/data/real)")
    parser.add_argument("--no-fpfh", action="store_true", help="the service only")
    parser.add_argument("--json", type=Path, help="write every row here")
    parser.add_argument("--odometry", nargs=2, type=float, metavar=("DEG", "METRES"),
                        help="send each request an initial_transform this far off the truth, as odometry would")
    args = parser.parse_args(argv)
    directory = scan_set(parser, args.dir)
    if not (directory / f"{PAIR}.npz").is_file():
        parser.error(f"no LiDAR pair {PAIR}.npz in the real-scan set {directory}")
    json_destination(args.json)
    refuse_fpfh_without_open3d(parser, args)
    made_by = provenance([bundled_models_dir() / "general"])  # before the run: the checkout may move on during it
    cases = ((label, "lidar", src, tgt, truth) for label, src, tgt, truth in variants(directory))
    guess = None if args.odometry is None else odometry_guesses(*args.odometry)
    return report("lidar_variants", {"all": registered(cases, fpfh=not args.no_fpfh, guess=guess)}, args.json,
                  made_by)


if __name__ == "__main__":
    main()
