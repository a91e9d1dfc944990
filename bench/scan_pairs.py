"""The real-scan set's pairs, and the pairs derived from them: scans that no file pairs, ground truth chained.

A file ``<prefix>_<j>_<i>.npz`` holds scan ``j`` as ``source`` and scan ``i`` as ``target`` of one object or scene, with
``transform`` taking the source onto the target (the set's README). Where two files hold the same scan (the same
prefix and label, the same points), their ground truths chain: :func:`derived_pairs` pairs every two scans of a
prefix that no file pairs, ``<prefix>_<j>_<i>`` with the larger label as the source (as the set names its pairs), and
``T_ji = inv(M_i) @ M_j``, ``M_k`` scan ``k``'s pose in the frame of the first scan reached. In the set beside this
repository these are the dragon's range images 72-168 deg apart on the turntable (its own pairs are 24 and 48 deg
apart): wider baselines, less overlap, and pairs that no default was chosen on.
"""

from __future__ import annotations

import hashlib
import re
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PAIR_NAME = re.compile(r"^(?P<prefix>.+)_(?P<source>\d+)_(?P<target>\d+)$")  # <prefix>_<j>_<i>


@dataclass(frozen=True)
class ScanPair:
    """Two scans and the ground truth ``src_to_tgt [4, 4]`` (``target ~= R source + t``)."""

    name: str
    sensor: str
    source: np.ndarray  # [N, 3] float32
    target: np.ndarray  # [M, 3] float32
    src_to_tgt: np.ndarray  # [4, 4] float64


def read_pairs(directory: Path, names: list[str] | None = None) -> list[ScanPair]:
    """Every ``*.npz`` pair of ``directory`` (or only those whose file stem is in ``names``), in file-name order."""
    pairs = []
    for file in sorted(Path(directory).glob("*.npz")):
        if names and file.stem not in names:
            continue
        with np.load(file) as data:
            pairs.append(ScanPair(file.stem, str(data["sensor"]), data["source"].astype(np.float32),
                                  data["target"].astype(np.float32), data["transform"].astype(np.float64)))
    return pairs


@dataclass(frozen=True)
class _Scan:
    prefix: str
    label: int
    digest: str  # of the points: a label reused with other points is another scan


def _scan(prefix: str, label: str, points: np.ndarray) -> _Scan:
    return _Scan(prefix, int(label), hashlib.sha256(np.ascontiguousarray(points).tobytes()).hexdigest())


def derived_pairs(directory: Path) -> list[ScanPair]:
    """The pairs of scans of ``directory`` that share a prefix and a chain of its pairs but no file (see the module's
    docstring), by prefix and then by source and target label."""
    clouds: dict[_Scan, np.ndarray] = {}
    sensors: dict[str, str] = {}
    moves: dict[_Scan, list[tuple[_Scan, np.ndarray]]] = {}  # scan -> [(neighbour, scan_to_neighbour [4, 4])]
    for pair in read_pairs(directory):
        named = PAIR_NAME.match(pair.name)
        if named is None:
            continue
        source = _scan(named["prefix"], named["source"], pair.source)
        target = _scan(named["prefix"], named["target"], pair.target)
        clouds[source], clouds[target] = pair.source, pair.target
        sensors[named["prefix"]] = pair.sensor
        moves.setdefault(source, []).append((target, pair.src_to_tgt))
        moves.setdefault(target, []).append((source, np.linalg.inv(pair.src_to_tgt)))
    derived: list[tuple[tuple[str, int, int], ScanPair]] = []
    seen: set[_Scan] = set()
    for first in sorted(moves, key=lambda s: (s.prefix, s.label, s.digest)):
        if first in seen:
            continue
        in_first = _poses(first, moves)  # every scan chained to ``first`` -> scan_to_first [4, 4]
        seen.update(in_first)
        for j in in_first:
            for i in in_first:
                if i.label >= j.label or any(other == i for other, _ in moves[j]):
                    continue  # the larger label is the source; a pair the set holds is not derived
                pair = ScanPair(f"{j.prefix}_{j.label}_{i.label}", sensors[j.prefix], clouds[j], clouds[i],
                                np.linalg.inv(in_first[i]) @ in_first[j])
                derived.append(((j.prefix, j.label, i.label), pair))
    return [pair for _, pair in sorted(derived, key=lambda item: item[0])]


def _poses(first: _Scan, moves: dict[_Scan, list[tuple[_Scan, np.ndarray]]]) -> dict[_Scan, np.ndarray]:
    """Each scan reachable from ``first`` through the pairs, with its pose in ``first``'s frame ``[4, 4]``
    (breadth first: the fewest pairs chained)."""
    poses, queue = {first: np.eye(4)}, deque([first])
    while queue:
        scan = queue.popleft()
        for neighbour, scan_to_neighbour in moves[scan]:
            if neighbour not in poses:  # neighbour -> scan -> first
                poses[neighbour] = poses[scan] @ np.linalg.inv(scan_to_neighbour)
                queue.append(neighbour)
    return poses
