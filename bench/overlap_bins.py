"""Recall by overlap: ``python -m bench.overlap_bins PAIRS NAME=PER_PAIR.npz [NAME=PER_PAIR.npz ...]``.

Each pair of ``PAIRS`` (``mfgnet make-pairs``) gets its overlap: the share of its source points that the true pose
places within ``--distance`` (default 0.05, the pairs' unit) of a target point. The pairs are put in bins at
``--edges`` (default 0.5 0.7 0.9: below 0.5, 0.5-0.7, 0.7-0.9, 0.9 and above), and each method's results on the same
pairs (``mfgnet evaluate --pairs PAIRS --per-pair PER_PAIR.npz``, its own or a baseline's) give the recall of each bin
at 5 deg and 0.05 and at 1 deg and 0.01, as ``mfgnet evaluate`` counts them. Example, ``docs/ACCURACY.md``'s scans:

    mfgnet make-pairs --setting scans --seed 0 --out scans170.npz
    mfgnet evaluate --model general --refine icp-plane --pairs scans170.npz --per-pair general.npz
    OMP_NUM_THREADS=1 mfgnet evaluate --baseline fpfh-ransac-icp --pairs scans170.npz --per-pair fpfh.npz
    python -m bench.overlap_bins scans170.npz general=general.npz fpfh-ransac-icp=fpfh.npz
"""

from __future__ import annotations

import argparse
from itertools import pairwise
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from bench.report_io import checked, emit_report, json_destination, positive_float
from model.cli_inputs import input_file, pairs_file, require_zip
from model.metrics import recall_hits


def overlaps(pairs: dict[str, np.ndarray], distance: float) -> np.ndarray:
    """``[M]`` per pair, the share of its source points the true pose places within ``distance`` of a target point."""
    shares = []
    for source, target, rotation, translation in zip(pairs["source"], pairs["target"], pairs["rotation"],
                                                     pairs["translation"], strict=True):
        moved = source.astype(np.float64) @ rotation.T + translation  # [N, 3] in the target's frame
        nearest, _ = cKDTree(target).query(moved, distance_upper_bound=distance)  # [N], inf beyond the distance
        shares.append(float(np.mean(nearest < distance)))
    return np.array(shares)


def bin_names(edges: list[float]) -> list[str]:
    """``["< 0.5", "0.5-0.7", "0.7-0.9", ">= 0.9"]`` for edges ``[0.5, 0.7, 0.9]``."""
    return [f"< {edges[0]:g}", *(f"{lo:g}-{hi:g}" for lo, hi in pairwise(edges)),
            f">= {edges[-1]:g}"]


def recall_by_overlap(overlap: np.ndarray, results: dict[str, dict[str, np.ndarray]], edges: list[float]
                      ) -> list[dict]:
    """Per bin of ``overlap [M]`` at ``edges``: its pairs and each method's recalls (``results``: a method's
    ``rotation_error_deg [M]`` and ``translation_error [M]``)."""
    which = np.digitize(overlap, edges)  # [M] 0 .. len(edges)
    hits = {name: recall_hits(r["rotation_error_deg"], r["translation_error"]) for name, r in results.items()}
    rows = []
    for k, name in enumerate(bin_names(edges)):
        members = which == k  # [M]
        count = int(members.sum())
        rows.append({"overlap": name, "pairs": count, "methods": {
            method: {key: round(float(hit[members].mean()), 3) if count else None for key, hit in by_key.items()}
            for method, by_key in hits.items()}})
    return rows


def method_results(parser: argparse.ArgumentParser, given: list[str], pair_count: int
                   ) -> dict[str, dict[str, np.ndarray]]:
    """``NAME=PER_PAIR.npz`` arguments read, each holding one result per pair of the pairs file; else a usage
    error naming the argument."""
    results = {}
    for text in given:
        name, sep, path = text.partition("=")
        if not sep or not name or not path:
            parser.error(f"{text!r}: expected NAME=PER_PAIR.npz (mfgnet evaluate --per-pair's file)")
        if name in results:
            parser.error(f"{name!r} is given twice")
        checked(require_zip, checked(input_file, Path(path), name), name, "a per-pair file of mfgnet evaluate")
        try:
            with np.load(path, allow_pickle=False) as data:
                errors = {key: np.asarray(data[key], dtype=np.float64)
                          for key in ("rotation_error_deg", "translation_error")}
        except (OSError, ValueError, KeyError) as err:
            parser.error(f"{name}={path}: not a per-pair file of mfgnet evaluate ({str(err)[:120]})")
        if any(values.shape != (pair_count,) for values in errors.values()):
            parser.error(f"{name}={path}: {len(errors['rotation_error_deg'])} results for {pair_count} pairs: "
                         "evaluate it on the same pairs file")
        results[name] = errors
    return results


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", type=Path, help="the pairs file (mfgnet make-pairs)")
    parser.add_argument("results", nargs="+", metavar="NAME=PER_PAIR.npz",
                        help="a method's per-pair results on those pairs (mfgnet evaluate --per-pair)")
    parser.add_argument("--distance", type=positive_float, default=0.05,
                        help="a source point overlaps within this distance of a target point (the pairs' unit)")
    parser.add_argument("--edges", type=float, nargs="+", default=[0.5, 0.7, 0.9], help="bin edges, increasing")
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)
    if any(not 0 < e < 1 for e in args.edges) or list(args.edges) != sorted(set(args.edges)):
        parser.error(f"--edges must increase strictly within (0, 1), got {args.edges}")
    json_destination(args.json)
    pairs = checked(pairs_file, args.pairs, "PAIRS")
    results = method_results(parser, args.results, len(pairs["source"]))
    overlap = overlaps(pairs, args.distance)
    report = {"benchmark": "overlap_bins", "pairs": str(args.pairs), "distance": args.distance,
              "edges": args.edges, "bins": recall_by_overlap(overlap, results, args.edges)}
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
