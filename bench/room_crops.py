"""Pairs cut from one room fragment, with exact ground truth: ``python -m bench.room_crops [DIR]``.

The real-scan set (``DIR``, else ``$MFGNET_REAL_DATA``, else ``../shared/data/real``) holds four indoor pairs (the
sensor class of 3DMatch and 3DLoMatch: ``kinect-*``, ``xtion-*``), eight fused room fragments. Each fragment (every
cloud once, source and target of each pair, a scan two pairs share once) gives pairs cut from itself:

- two overlapping windows along a seeded direction in the plane of its two largest principal axes (the room's
  floor plan, mostly): with the points projected on it, window A keeps the lowest share ``a``, window B the highest
  ``a``, so that the points in both are ``--overlaps`` (default 30%, 50%, 70%) of each window (``a = 1 / (2 - o)``);
- each window resampled on its own surface, independently of the other (:func:`resampled`: made 4x denser on its
  tangent discs by :func:`bench.surface_resample.densified`, then reduced to voxel means on a grid of its own seeded
  offset, sized so the window keeps about its own point count): the two clouds share no point and no noise, as two
  fused fragments of one room do not;
- window A, the source, moved by a seeded rigid motion about its centroid as consecutive fragments are apart
  (``cut``: 5-25 deg about the fragment's third principal axis, the vertical of a floor plan, a tilt of up to 5 deg
  and 0.2-0.8 m; the set's 3DMatch pairs are 18-25 deg and 0.5-0.8 m apart), and that again turned about its
  centroid by ``--turns`` seeded Haar-uniform rotations (:func:`bench.real_scans.turned`: ``turned``,
  ``turned-2``, ...).

Every case is registered in process (:mod:`bench.variant_runs`) with the service's defaults and, unless
``--no-fpfh``, by FPFH + RANSAC + ICP; success by the indoor thresholds (15 deg, 0.3 m). It prints one row per case
and the totals per overlap, per fragment and over all; ``--json`` writes them::

    python -m bench.room_crops --json results/general-0.2.0/room_crops.json
    python -m bench.room_crops --overlaps 0.5 --turns 1 --fragments 3dm_hotel3_15_8/source --no-fpfh

The points are real and the truth exact; the pairs are made up: one fragment's two windows saw the room from one
fused trajectory, so their points agree more closely than two fragments' do, and the windows' edges are straight
cuts, not a sensor's field of view. A held-out proxy for 3DMatch-like pairs of other rooms, not a replacement.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench.baselines import refuse_fpfh_without_open3d
from bench.real_scans import INDOOR_THRESHOLDS, fpfh_ransac_icp, scan_set, thresholds, turned
from bench.report_io import json_destination, machine_info, non_negative_int, positive_int, provenance
from bench.scan_pairs import read_pairs
from bench.surface_resample import densified, point_spacing
from bench.variant_runs import general_registrar, registered, report, totals
from service.manifest import bundled_models_dir

OVERLAPS = (0.3, 0.5, 0.7)  # the points in both windows, a share of each window
DENSER = 4  # a window's points per original point before its voxel means
YAW_DEG, TILT_DEG, SHIFT_M = (5.0, 25.0), 5.0, (0.2, 0.8)  # the `cut` motion's ranges


def fragments(directory: Path, names: list[str] | None = None) -> list[tuple[str, str, np.ndarray]]:
    """``(name, sensor, points [N, 3] float64)`` of every cloud of the set's indoor pairs (``<pair>/source``,
    ``<pair>/target``; a cloud two pairs share once, by its points), or only those of ``names``."""
    found, seen = [], set()
    for pair in read_pairs(directory):
        if thresholds_of(pair.sensor) != INDOOR_THRESHOLDS:
            continue
        for side, cloud in (("source", pair.source), ("target", pair.target)):
            key = hashlib.sha1(np.ascontiguousarray(cloud[np.lexsort(cloud.T)]).tobytes()).hexdigest()
            name = f"{pair.name}/{side}"
            if key in seen or (names and name not in names):
                continue
            seen.add(key)
            found.append((name, pair.sensor, cloud.astype(np.float64)))
    return found


def thresholds_of(sensor: str) -> tuple[float, float] | None:
    """The sensor's class thresholds (:func:`bench.real_scans.thresholds`), ``None`` for a sensor of no class."""
    try:
        return thresholds(sensor)
    except ValueError:
        return None


def principal_axes(points: np.ndarray) -> np.ndarray:
    """``[3, 3]`` rows: the principal axes of ``points [N, 3]``, largest spread first."""
    values, vectors = np.linalg.eigh(np.cov(points.T))
    return vectors[:, np.argsort(values)[::-1]].T


def windows(points: np.ndarray, overlap: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Indices of windows A and B of ``points [N, 3]``: along a seeded unit direction in the plane of its two largest
    principal axes, A the lowest share ``a = 1 / (2 - overlap)`` of the points, B the highest ``a``; the points in
    both are ``overlap`` of each (ties aside)."""
    axes = principal_axes(points)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    along = (points - points.mean(axis=0)) @ (np.cos(angle) * axes[0] + np.sin(angle) * axes[1])  # [N]
    order = np.argsort(along, kind="stable")
    keep = round(len(points) / (2.0 - overlap))
    return np.sort(order[:keep]), np.sort(order[len(points) - keep :])


def voxel_means(points: np.ndarray, voxel: float, offset: np.ndarray) -> np.ndarray:
    """The mean of the points of ``points [N, 3]`` in each cell of a grid of side ``voxel`` shifted by
    ``offset [3]``."""
    cells = np.floor((points - offset) / voxel).astype(np.int64)  # [N, 3]
    _, cell, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, cell.ravel(), points)
    return sums / counts[:, None]


def resampled(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``points [N, 3]`` drawn again on their own surface: ``DENSER`` times as many on their tangent discs
    (:func:`densified`), then the voxel means of a grid of a seeded offset whose side gives about ``N`` of them (one
    trial grid of twice the spacing, its side then scaled by the square root of the count over ``N``); float64."""
    dense = densified(points, DENSER * len(points), rng).astype(np.float64)
    offset = rng.random(3)
    trial = 2.0 * point_spacing(points)
    voxel = trial * np.sqrt(len(voxel_means(dense, trial, offset * trial)) / len(points))  # a surface: N ~ 1 / side^2
    return voxel_means(dense, voxel, offset * voxel)


def cut_motion(points: np.ndarray, vertical: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``[4, 4]``: a seeded motion of ``points [N, 3]`` about their centroid as consecutive fragments are apart: a
    turn of ``YAW_DEG`` (either way) about the unit axis ``vertical [3]``, a tilt of up to ``TILT_DEG`` about a seeded
    axis, and a move of ``SHIFT_M`` metres in a seeded direction."""
    yaw = Rotation.from_rotvec(np.radians(rng.uniform(*YAW_DEG) * rng.choice([-1.0, 1.0])) * vertical)
    tilt_axis = rng.normal(size=3)
    tilt = Rotation.from_rotvec(np.radians(rng.uniform(0.0, TILT_DEG)) * tilt_axis / np.linalg.norm(tilt_axis))
    direction = rng.normal(size=3)
    centre = points.mean(axis=0)
    motion = np.eye(4)
    motion[:3, :3] = (tilt * yaw).as_matrix()
    motion[:3, 3] = centre - motion[:3, :3] @ centre + rng.uniform(*SHIFT_M) * direction / np.linalg.norm(direction)
    return motion


def crop_pair(
    points: np.ndarray, overlap: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(source [N, 3], target [M, 3], src_to_tgt [4, 4])`` cut from one fragment ``points``: window A resampled and
    moved by :func:`cut_motion` about the fragment's third principal axis (the source), window B resampled where it
    lies (the target), float32 clouds."""
    a, b = windows(points, overlap, rng)
    source, target = resampled(points[a], rng), resampled(points[b], rng)
    motion = cut_motion(source, principal_axes(points)[2], rng)
    moved = source @ motion[:3, :3].T + motion[:3, 3]
    return moved.astype(np.float32), target.astype(np.float32), np.linalg.inv(motion)


def cases(
    directory: Path, overlap: float, seed: int = 0, turns: int = 1, names: list[str] | None = None
) -> Iterator[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(label, sensor, source, target, src_to_tgt)`` per fragment at ``overlap``: as cut and turned ``turns``
    times (labels ``<fragment>/o<percent>/cut``, ``.../turned``, ``.../turned-2``...), seeded by ``seed``, the
    fragment and the overlap (a fragment's cases are the same whichever others run)."""
    percent = round(100 * overlap)
    for name, sensor, points in fragments(directory, names):
        rng = np.random.default_rng([seed, zlib.crc32(name.encode()), percent])
        source, target, truth = crop_pair(points, overlap, rng)
        yield f"{name}/o{percent}/cut", sensor, source, target, truth
        for k in range(1, turns + 1):
            src_t, truth_t = turned(source, truth, Rotation.random(random_state=rng).as_matrix())
            yield f"{name}/o{percent}/turned{'' if k == 1 else f'-{k}'}", sensor, src_t, target, truth_t


def overlap_share(text: str) -> float:
    """An argparse ``type``: an overlap share strictly between 0 and 1."""
    value = float(text)
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"must be a share between 0 and 1 (e.g. 0.5), got {text}")
    return value


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", help="real-scan set (default: $MFGNET_REAL_DATA or ../shared/data/real)")
    parser.add_argument(
        "--overlaps",
        type=overlap_share,
        nargs="+",
        default=list(OVERLAPS),
        help="the points in both windows, a share of each window (default 0.3 0.5 0.7)",
    )
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the windows, motions and turns")
    parser.add_argument("--turns", type=positive_int, default=3, help="turned cases per fragment and overlap")
    parser.add_argument("--fragments", nargs="+", help="only these clouds (<pair>/source or <pair>/target)")
    parser.add_argument("--no-fpfh", action="store_true", help="the service only")
    parser.add_argument("--json", type=Path, help="write every row here")
    args = parser.parse_args(argv)
    directory = scan_set(parser, args.dir)
    known = [name for name, _, _ in fragments(directory)]
    if not known:
        parser.error(f"no indoor pair (kinect-*, xtion-*) in the real-scan set {directory}")
    unknown = [name for name in args.fragments or [] if name not in known]
    if unknown:
        parser.error(f"--fragments: no indoor cloud {', '.join(unknown)} (there: {', '.join(known)})")
    json_destination(args.json)
    refuse_fpfh_without_open3d(parser, args)
    made_by = provenance(
        [bundled_models_dir() / "general"]
    )  # before the run: the shared checkout may move on during it
    registrar = general_registrar()
    first = fragments(directory, args.fragments or known[:1])[0][2].astype(np.float32)
    registrar.register(first, first, refine="icp-plane", rotation_search="auto")  # sets the runtime up, untimed
    if not args.no_fpfh:
        fpfh_ransac_icp(first, first)  # Open3D's import and first call, untimed (as bench.real_scans.run_fpfh)
    groups = {
        f"o{round(100 * o)}": registered(
            cases(directory, o, args.seed, args.turns, args.fragments), not args.no_fpfh, registrar
        )
        for o in args.overlaps
    }
    result = report("room_crops", groups, None)
    rows = result["rows"]
    fragment_names = list(dict.fromkeys(r["variant"].rsplit("/", 2)[0] for r in rows))
    result |= {
        "seed": args.seed,
        "turns": args.turns,
        "overlaps": args.overlaps,
        "units": "rotation errors in degrees; translation errors in metres; seconds (in process)",
        "machine": machine_info(2),
        "provenance": made_by,
        "totals_all": totals(rows),
        "by_fragment": {
            name: totals([r for r in rows if r["variant"].rsplit("/", 2)[0] == name]) for name in fragment_names
        },
        "by_variant": {
            kind: totals([r for r in rows if r["variant"].rsplit("/", 1)[1].startswith(kind)])
            for kind in ("cut", "turned")
        },
    }
    for key in ("totals_all", "by_variant", "by_fragment"):
        print(key, json.dumps(result[key]))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
