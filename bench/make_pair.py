"""Make a real-scan pair file from two clouds and their ground-truth pose, for ``python -m bench.real_scans DIR``.

The clouds may be in any format the service reads (``.ply .pcd .las .laz .e57 .xyz .txt .csv .pts .ptx .npy .npz``);
the pose is a 4x4 ``T_target_source`` (``target ~ R source + t``: the source moved onto the target, the service's
``transform``) in a ``.txt`` (four rows of four numbers), ``.npy`` or ``.json`` file, read as ``mfgnet register
--initial-transform`` reads one::

    python -m bench.make_pair scan_1.ply scan_0.ply --transform T_0_1.txt --sensor vlp16 --out pairs/lab_1_0.npz
    python -m bench.make_pair a.pcd b.pcd --transform pose.npy --sensor scanner-x --thresholds 2,0.005 \\
        --out pairs/part_a_b.npz

The file holds ``source`` and ``target`` (float32 ``[N, 3]``, ``[M, 3]``), ``transform`` (float64 ``[4, 4]``, its
rotation the nearest one to the given matrix's), ``sensor``, and with ``--thresholds DEG,DIST`` its own success
thresholds (``rotation_threshold_deg``, ``translation_threshold`` in the clouds' unit). Its name without ``.npz`` is
the pair's name in ``bench.real_scans``' table and for its ``--pairs``. It prints how closely the pose lays the
source onto the target, and warns where the inverse pose fits better (a ``T_source_target`` given by mistake).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from bench.scan_pairs import positive_thresholds
from service.checks import check_cloud, check_transform
from service.errors import InputError
from service.normalization import rms_radius
from service.pointcloud_io import PointCloudFormatError, read_points
from service.procrustes import to_matrix
from service.stages.float32_check import STEP_SHARE
from service.transform_file import TransformFileError, read_transform

FIT_POINTS = 2000  # source points whose distance to the target tells how closely the pose lays one onto the other


def cloud(parser: argparse.ArgumentParser, path: Path, name: str) -> np.ndarray:
    """The float64 ``[N, 3]`` points of ``path`` (``name``: ``SOURCE`` or ``TARGET``), or a usage error."""
    if path.is_dir():
        parser.error(f"{name} {path}: a folder, not a file")
    if path.exists() and not path.is_file():  # a FIFO's open() could block for ever
        parser.error(f"{name} {path}: not a regular file")
    try:
        return check_cloud(read_points(path), f"{name} {path.name}")
    except (PointCloudFormatError, InputError) as err:
        parser.error(f"{name}: {err}")
    except OSError as err:
        parser.error(f"{name} {path}: cannot read it: {err.strerror or err}")


def pose(parser: argparse.ArgumentParser, path: Path) -> np.ndarray:
    """The rigid ``[4, 4]`` pose in ``path`` (its rotation the nearest to the matrix's), or a usage error."""
    try:
        R, t = check_transform(read_transform(path))
    except TransformFileError as err:
        parser.error(f"--transform {path.name}: {err}")
    except InputError as err:
        parser.error(f"--transform {path.name}: not a rigid pose ({str(err).removeprefix('initial_transform ')})")
    return to_matrix(R, t)


def thresholds_pair(text: str) -> tuple[float, float]:
    """An argparse ``type`` for ``--thresholds DEG,DIST``: two positive numbers."""
    return positive_thresholds(text, text, "5,0.01")


def fit(source: np.ndarray, target: np.ndarray, transform: np.ndarray, seed: int = 0) -> float:
    """Median distance from up to :data:`FIT_POINTS` source points, moved by ``transform``, to their nearest target
    point (the clouds' unit)."""
    rng = np.random.default_rng(seed)
    picked = source[rng.choice(len(source), min(FIT_POINTS, len(source)), replace=False)]  # [P, 3]
    moved = picked @ transform[:3, :3].T + transform[:3, 3]
    return float(np.median(cKDTree(target).query(moved)[0]))


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m bench.make_pair", description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, metavar="SOURCE", help="the cloud the pose moves (any format read)")
    parser.add_argument("target", type=Path, metavar="TARGET", help="the cloud it moves onto")
    parser.add_argument(
        "--transform",
        type=Path,
        required=True,
        metavar="POSE",
        help="4x4 T_target_source (target ~ R source + t): .txt (4 rows of 4 numbers), .npy or "
        ".json (a 4x4 list, or an object with 'transform'), as mfgnet register "
        "--initial-transform reads",
    )
    parser.add_argument(
        "--sensor",
        required=True,
        help="the sensor's name: cyberware-range, kinect-*, xtion-* or lidar are judged by their "
        "class's thresholds in metres (docs/REAL_SCANS.md); any other needs --thresholds here or "
        "in bench.real_scans",
    )
    parser.add_argument(
        "--thresholds",
        type=thresholds_pair,
        metavar="DEG,DIST",
        help="this pair's success thresholds: rotation error < DEG degrees and translation error < "
        "DIST in the clouds' unit",
    )
    parser.add_argument("--out", type=Path, required=True, help="the pair file to write (.npz)")
    args = parser.parse_args(argv)
    if not args.sensor.strip():
        parser.error("--sensor must not be empty")
    if args.out.suffix != ".npz":
        parser.error(f"--out {args.out}: must end in .npz (bench.real_scans reads a folder's *.npz files)")
    if args.out.is_dir():
        parser.error(f"--out {args.out}: a folder, not a file")
    if not args.out.parent.is_dir():
        parser.error(f"--out {args.out}: folder {args.out.parent} does not exist")
    source, target = cloud(parser, args.source, "SOURCE"), cloud(parser, args.target, "TARGET")
    transform = pose(parser, args.transform)
    fields = {}
    if args.thresholds:
        fields = {"rotation_threshold_deg": args.thresholds[0], "translation_threshold": args.thresholds[1]}
    source32, target32 = source.astype(np.float32), target.astype(np.float32)
    rounding = max(float(np.abs(source32 - source).max()), float(np.abs(target32 - target).max()))
    try:
        with open(args.out, "wb") as out:
            np.savez(out, source=source32, target=target32, transform=transform, sensor=np.str_(args.sensor), **fields)
    except OSError as err:
        parser.exit(1, f"{parser.prog}: error: cannot write {args.out}: {err.strerror or err}\n")
    closeness, inverse = fit(source, target, transform), fit(source, target, np.linalg.inv(transform))
    print(
        f"wrote {args.out}: {len(source)} source and {len(target)} target points, sensor {args.sensor!r}"
        + (f", thresholds {args.thresholds[0]:g} deg and {args.thresholds[1]:g}" if args.thresholds else "")
        + f"; float32 moved coordinates by at most {rounding:.3g}; median distance of the moved source to the "
        f"target {closeness:.4g} (with the inverse pose {inverse:.4g})"
    )
    radius = min(rms_radius(source), rms_radius(target))
    if rounding >= STEP_SHARE * radius:
        print(
            f"warning: float32 moved coordinates by up to {rounding:.3g}, {rounding / radius:.2g} of the smaller "
            f"cloud's RMS radius ({radius:.4g}): the pair no longer holds the clouds' shape; move both clouds by one "
            "offset first (and the pose with them)",
            file=sys.stderr,
        )
    if min(closeness, inverse) >= radius:
        print(
            f"warning: neither {args.transform.name} nor its inverse lays the source onto the target (median "
            f"distance {closeness:.4g}, more than the smaller cloud's RMS radius {radius:.4g}): check the pose's "
            "frames and units; clouds moved by an offset need the pose moved with them (t' = t + R o - o)",
            file=sys.stderr,
        )
    elif inverse < 0.5 * closeness:
        print(
            f"warning: the inverse of {args.transform.name} lays the source more closely onto the target: is it "
            "T_source_target? --transform takes T_target_source (target ~ R source + t)",
            file=sys.stderr,
        )
    return args.out


if __name__ == "__main__":
    main()
