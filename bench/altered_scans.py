"""The real-scan set's pairs altered as other sensors and scenes would alter them: ``python -m bench.altered_scans``.

Each pair of the set (``DIR``, else ``$MFGNET_REAL_DATA``, else ``../shared/data/real``) is altered in one of these
ways, seeded per alteration and pair, and registered as altered and with the source turned about its centroid by a
seeded Haar rotation (in process, :mod:`bench.variant_runs`: the service's defaults beside FPFH + RANSAC + ICP,
``--no-fpfh`` to skip):

- ``sparse30``, ``sparse10``: each cloud keeps a random 30% / 10% of its points (a sparser scanner);
- ``source10``: the source keeps a random 10% of its points, the target all of them (a sparse scan against a dense
  one, as a LiDAR frame against a map);
- ``noise``: Gaussian noise of one point spacing (the cloud's median nearest-neighbour distance) per coordinate;
- ``crop``: the source keeps the 60% of its points on one side of a plane through its centroid, of random normal
  (less overlap);
- ``croptarget``: the same cut of the target, the source whole (a scan larger than what it is registered to);
- ``scattered``: each cloud gets ``--scattered`` (default 0.1) times its points more, uniform in its bounding box
  (flying pixels, spurious returns).

Success: the data README's thresholds for the pair's sensor. The points are real; the alterations are made up, to
find where the defaults break before a user's scans do.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench.baselines import refuse_fpfh_without_open3d
from bench.real_scans import scan_set, thresholds, turned
from bench.report_io import json_destination, provenance
from bench.scan_pairs import THRESHOLD_FIELDS, read_pair, read_pairs
from bench.surface_resample import point_spacing
from bench.variant_runs import general_registrar, registered, report
from service.manifest import bundled_models_dir

ALTERATIONS = ("sparse30", "sparse10", "noise", "crop", "scattered", "source10", "croptarget")
CROP_KEEP = 0.6  # share of the cut cloud's points that `crop` (the source) and `croptarget` (the target) keep


def altered(kind: str, source: np.ndarray, target: np.ndarray, rng: np.random.Generator,
            scattered: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """``source [N, 3]`` and ``target [M, 3]`` altered by ``kind`` (one of ``ALTERATIONS``), float32; the points keep
    their frames, so the pair's ground truth holds."""
    if kind.startswith("sparse"):
        keep = int(kind.removeprefix("sparse")) / 100
        return source[rng.random(len(source)) < keep], target[rng.random(len(target)) < keep]
    if kind == "source10":
        return source[rng.random(len(source)) < 0.1], target
    if kind == "noise":
        def noisy(c: np.ndarray) -> np.ndarray:
            return (c + rng.normal(0.0, point_spacing(c), c.shape)).astype(np.float32)
        return noisy(source), noisy(target)
    if kind in ("crop", "croptarget"):
        cut = source if kind == "crop" else target
        normal = rng.normal(size=3)
        side = (cut - cut.mean(axis=0)) @ (normal / np.linalg.norm(normal))  # [N]
        cut = cut[side < np.quantile(side, CROP_KEEP)]
        return (cut, target) if kind == "crop" else (source, cut)
    if kind == "scattered":
        def with_scattered(c: np.ndarray) -> np.ndarray:
            extra = rng.uniform(c.min(axis=0), c.max(axis=0), size=(int(len(c) * scattered), 3))
            return np.concatenate([c, extra]).astype(np.float32)
        return with_scattered(source), with_scattered(target)
    raise ValueError(f"unknown alteration {kind!r}; one of {', '.join(ALTERATIONS)}")


def cases(directory: Path, kind: str, scattered: float = 0.1, names: list[str] | None = None
          ) -> Iterator[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(label, sensor, source, target, src_to_tgt)`` of every pair altered by ``kind``, as altered and turned."""
    for file in sorted(directory.glob("*.npz")):
        if names and file.stem not in names:
            continue
        rng = np.random.default_rng([ALTERATIONS.index(kind), sum(map(ord, file.stem))])
        pair = read_pair(file)  # with the file's own thresholds, which judge it before its sensor class's
        source, target = altered(kind, pair.source, pair.target, rng, scattered)
        yield f"{kind}/{file.stem}/scanned", pair.sensor, source, target, pair.src_to_tgt, pair.limits
        src_t, truth_t = turned(source, pair.src_to_tgt, Rotation.random(random_state=rng).as_matrix())
        yield f"{kind}/{file.stem}/turned", pair.sensor, src_t, target, truth_t, pair.limits


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", help="real-scan set (default: $MFGNET_REAL_DATA or ../shared/data/real)")
    parser.add_argument("--alterations", nargs="+", choices=ALTERATIONS, default=list(ALTERATIONS))
    parser.add_argument("--scattered", type=float, default=0.1, help="scattered points per point (`scattered`)")
    parser.add_argument("--pairs", nargs="+", help="only these pairs (file stems)")
    parser.add_argument("--no-fpfh", action="store_true", help="the service only")
    parser.add_argument("--json", type=Path, help="write every row here")
    args = parser.parse_args(argv)
    directory = scan_set(parser, args.dir, args.pairs)
    for pair in read_pairs(directory, args.pairs):  # before any registration, as bench.real_scans refuses them
        if pair.limits is None:
            try:
                thresholds(pair.sensor)
            except ValueError as err:
                parser.error(f"{pair.name}: {err}; give them with {' and '.join(THRESHOLD_FIELDS)} in its pair file")
    json_destination(args.json)
    refuse_fpfh_without_open3d(parser, args)
    made_by = provenance([bundled_models_dir() / "general"])  # before the run: the checkout may move on during it
    registrar = general_registrar()
    groups = {kind: registered(cases(directory, kind, args.scattered, args.pairs), not args.no_fpfh, registrar)
              for kind in args.alterations}
    return report("altered_scans", groups, args.json, made_by)


if __name__ == "__main__":
    main()
