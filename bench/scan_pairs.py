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

import argparse
import hashlib
import re
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.checks import check_transform
from service.errors import InputError

PAIR_NAME = re.compile(r"^(?P<prefix>.+)_(?P<source>\d+)_(?P<target>\d+)$")  # <prefix>_<j>_<i>


@dataclass(frozen=True)
class ScanPair:
    """Two scans and the ground truth ``src_to_tgt [4, 4]`` (``target ~= R source + t``)."""

    name: str
    sensor: str
    source: np.ndarray  # [N, 3] float32
    target: np.ndarray  # [M, 3] float32
    src_to_tgt: np.ndarray  # [4, 4] float64
    limits: tuple[float, float] | None = None  # the file's own success thresholds: (rotation deg, translation)


THRESHOLD_FIELDS = ("rotation_threshold_deg", "translation_threshold")  # optional in a pair file, both or neither


def positive_thresholds(values: str, text: str, example: str) -> tuple[float, float]:
    """``DEG,DIST`` of a ``--thresholds`` option as ``(degrees, distance)``, both positive and finite; else an
    ``argparse.ArgumentTypeError`` quoting the option's ``text`` and an ``example`` of it."""
    parts = values.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r}: expected DEG,DIST, two numbers (e.g. {example})")
    try:
        degrees, distance = float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: DEG and DIST must be numbers (e.g. {example})") from None
    if not (np.isfinite(degrees) and np.isfinite(distance) and degrees > 0 and distance > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: DEG and DIST must be positive")
    return degrees, distance


def read_pairs(directory: Path, names: list[str] | None = None) -> list[ScanPair]:
    """Every ``*.npz`` pair of ``directory`` (or only those whose file stem is in ``names``), in file-name order;
    ``ValueError`` naming the file and what is wrong with it for one that is no pair (:func:`read_pair`)."""
    return [read_pair(file) for file in sorted(Path(directory).glob("*.npz")) if not names or file.stem in names]


def read_pair(file: Path) -> ScanPair:
    """The pair in ``file``: ``source [N, 3]`` and ``target [M, 3]`` finite points (N, M >= 1), ``transform [4, 4]``
    finite, ``sensor`` a string (the set's README), and optionally both ``rotation_threshold_deg`` and
    ``translation_threshold`` (positive numbers; the latter in the clouds' unit) as the pair's success thresholds;
    else ``ValueError`` naming the file and the problem."""
    import zipfile

    def refuse(problem: str) -> ValueError:
        return ValueError(f"{file}: not a scan pair ({problem})")

    try:
        with open(file, "rb") as head:
            if head.read(4) != b"PK\x03\x04":  # np.load would take text for a pickle, an .npy for an array
                raise refuse("not an .npz archive")
        with np.load(file, allow_pickle=False) as data:
            missing = [key for key in ("source", "target", "transform", "sensor") if key not in data.files]
            if missing:
                raise refuse(f"no {', '.join(missing)}")
            arrays = {key: data[key] for key in ("source", "target", "transform", "sensor", *THRESHOLD_FIELDS)
                      if key in data.files}
    except (OSError, zipfile.BadZipFile, EOFError) as err:
        raise refuse(f"cannot read it: {err}") from None
    except ValueError as err:  # an object array (np.load refuses pickles); ours name the file already
        if str(err).startswith(str(file)):
            raise
        raise refuse(f"an array it cannot read: {str(err).split('. ')[0]}") from None
    for key in ("source", "target"):
        cloud = arrays[key]
        if cloud.ndim != 2 or cloud.shape[1] != 3 or len(cloud) == 0 or cloud.dtype.kind not in "fiu":
            raise refuse(f"{key} is {cloud.dtype} {list(cloud.shape)}, not [N, 3] numbers")
        with np.errstate(over="ignore"):
            as_uploaded = cloud.astype(np.float32)  # as the benchmark reads and uploads it
        if not np.isfinite(as_uploaded).all():
            raise refuse(f"{key} has {int((~np.isfinite(as_uploaded).all(axis=1)).sum())} rows that are not finite "
                         "as float32")
        arrays[key] = as_uploaded
    transform, sensor = arrays["transform"], arrays["sensor"]
    if transform.shape != (4, 4) or transform.dtype.kind not in "fiu" or not np.isfinite(transform).all():
        raise refuse(f"transform is {transform.dtype} {list(transform.shape)}, not a finite [4, 4]")
    try:  # as bench.make_pair and mfgnet register --initial-transform take a pose; the file's values are kept
        check_transform(transform)
    except InputError as err:
        raise refuse(f"transform is not a rigid pose ({str(err).removeprefix('initial_transform ')})") from None
    if sensor.shape != () or sensor.dtype.kind != "U":
        raise refuse(f"sensor is {sensor.dtype} {list(sensor.shape)}, not a string")
    given = [key for key in THRESHOLD_FIELDS if key in arrays]
    if len(given) == 1:
        raise refuse(f"{given[0]} without {next(k for k in THRESHOLD_FIELDS if k not in arrays)}: give both or neither")
    for key in given:
        value = arrays[key]
        if value.shape != () or value.dtype.kind not in "fiu" or not np.isfinite(value) or value <= 0:
            raise refuse(f"{key} is {value.dtype} {list(value.shape)} {value!s:.40}, not a positive number")
    limits = (float(arrays[THRESHOLD_FIELDS[0]]), float(arrays[THRESHOLD_FIELDS[1]])) if given else None
    return ScanPair(file.stem, str(sensor), arrays["source"].astype(np.float32), arrays["target"].astype(np.float32),
                    transform.astype(np.float64), limits)


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
    limits: dict[str, set[tuple[float, float] | None]] = {}  # prefix -> its files' own thresholds
    moves: dict[_Scan, list[tuple[_Scan, np.ndarray]]] = {}  # scan -> [(neighbour, scan_to_neighbour [4, 4])]
    for pair in read_pairs(directory):
        named = PAIR_NAME.match(pair.name)
        if named is None:
            continue
        source = _scan(named["prefix"], named["source"], pair.source)
        target = _scan(named["prefix"], named["target"], pair.target)
        clouds[source], clouds[target] = pair.source, pair.target
        sensors[named["prefix"]] = pair.sensor
        limits.setdefault(named["prefix"], set()).add(pair.limits)
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
                own = limits[j.prefix]  # the files' thresholds where they all give the same
                pair = ScanPair(f"{j.prefix}_{j.label}_{i.label}", sensors[j.prefix], clouds[j], clouds[i],
                                np.linalg.inv(in_first[i]) @ in_first[j], next(iter(own)) if len(own) == 1 else None)
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
