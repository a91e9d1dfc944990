"""A sequence of scans (odometry, a turntable) registered pair by pair: frame i (source) onto frame i-1 (target), the
relative poses ``T_{i-1}_i`` chained into frame 0's coordinates, ``T_0_i = T_0_{i-1} @ T_{i-1}_i``.

``mfgnet sequence`` (:mod:`service.cli`) runs it with one loaded model. Here: the frame checks made before any
registration, the chaining loop (one frame read at a time, the previous one kept as the next target) and the two
output formats, a JSON line per step and a KITTI odometry pose line per frame. Numpy only: the registration itself
comes in as a callable.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.formats import READ_SUFFIXES

# The kinds (text before the colon) of the service's warnings about an initial_transform (service.stages.guess_check,
# which this numpy-only module does not import)
FAR_FROM_PRIOR = "far from initial transform"
PRIOR_RETURNED = "initial transform returned"

# (frame index, path) -> [N, 3] points; raises on an unreadable file
ReadFrame = Callable[[int, Path], np.ndarray]
# (source [N, 3], target [M, 3], initial_transform [4, 4] list or None) -> the record of `mfgnet register --json`
RegisterPair = Callable[[np.ndarray, np.ndarray, list | None], dict]


def frame_problem(path: Path) -> str | None:
    """Why ``path`` cannot be a frame (missing, not a regular file, an extension no reader is named by), or ``None``.
    The content decides the format when the file is read; the extension is checked first so that a typo in a long
    list fails before the first registration instead of at its frame."""
    if not path.exists():
        return "no such file"
    if not path.is_file():
        return "a folder, not a file" if path.is_dir() else "not a regular file"
    if path.suffix.lower() not in READ_SUFFIXES:
        return f"unknown extension {path.suffix!r}; expected one of {' '.join(READ_SUFFIXES)}"
    return None


@dataclass(frozen=True)
class Step:
    """One registration of the sequence: frame ``index`` (source) onto frame ``index - 1`` (target)."""

    index: int
    source: Path
    target: Path
    record: dict  # the `mfgnet register --json` record of the pair: "transform" is T_{i-1}_i
    initial_transform: list | None  # [4, 4] the guess passed (--constant-velocity), else None
    accumulated: np.ndarray  # [4, 4] T_0_i: frame i in frame 0's coordinates
    source_centroid: np.ndarray  # [3] the mean of frame i's points, in its own coordinates
    accumulated_reliable: bool = True  # this step and every one before it reliable: T_0_i rests on no doubtful step

    @property
    def centroid_motion(self) -> float:
        """How far the step's pose moves the source's centroid: the frame's motion whatever its coordinates' origin
        (the translation alone grows with the origin's distance: kilometres for a turn of georeferenced frames)."""
        T = np.asarray(self.record["transform"], dtype=np.float64)  # [4, 4] T_{i-1}_i
        c = self.source_centroid
        return float(np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - c))

    @property
    def reliable(self) -> bool:
        return bool(self.record["quality"].get("reliable"))

    def json_line(self) -> str:
        """The step as one compact JSON line: ``index``, ``source``, ``target``, the pair's record, then
        ``initial_transform``, ``accumulated_transform`` and ``accumulated_reliable``."""
        line = {"index": self.index, "source": str(self.source), "target": str(self.target), **self.record,
                "initial_transform": self.initial_transform, "accumulated_transform": self.accumulated.tolist(),
                "accumulated_reliable": self.accumulated_reliable}
        return json.dumps(line, separators=(",", ":"))


def register_sequence(frames: Sequence[Path], read: ReadFrame, register: RegisterPair,
                      constant_velocity: bool = False) -> Iterator[Step]:
    """Register each frame onto the one before it, yielding each :class:`Step` as soon as it is done.

    Each frame is read once, when it first becomes the source (a path repeated next to itself is not read again: the
    pair is a frame onto itself). ``constant_velocity``: the previous step's relative pose is the next step's
    ``initial_transform`` (the usual odometry prior: the sensor keeps moving as it moved); the first step gets none,
    and the warnings about the guess say so (:func:`prior_warnings`). A step is ``accumulated_reliable`` while it and
    every step before it are reliable: one doubtful step moves every later ``T_0_i`` with it.
    """
    if len(frames) < 2:
        raise ValueError(f"a sequence needs at least two frames, got {len(frames)}")
    target_points = read(0, frames[0])  # [M, 3]
    T_0_target = np.eye(4)  # [4, 4] T_0_{i-1}
    previous: list | None = None  # [4, 4] T_{i-2}_{i-1}, the last step's relative pose
    chain_reliable = True  # every step so far reliable
    for index in range(1, len(frames)):
        same = frames[index] == frames[index - 1]
        source_points = target_points if same else read(index, frames[index])  # [N, 3]
        guess = previous if constant_velocity else None
        record = register(source_points, target_points, guess)
        T_0_source = T_0_target @ np.asarray(record["transform"], dtype=np.float64)  # T_0_i = T_0_{i-1} @ T_{i-1}_i
        centroid = np.asarray(source_points, dtype=np.float64)[:, :3].mean(axis=0)  # [3]
        if guess is not None:
            record = {**record, "warnings": prior_warnings(record, guess, centroid)}
        chain_reliable = chain_reliable and bool(record["quality"].get("reliable"))
        yield Step(index, frames[index], frames[index - 1], record, guess, T_0_source, centroid, chain_reliable)
        target_points, T_0_target, previous = source_points, T_0_source, record["transform"]


def prior_warnings(record: dict, prior: list, centroid: np.ndarray) -> list[str]:
    """The step's warnings with those about its ``initial_transform`` (``far from initial transform``, ``initial
    transform returned``: :mod:`service.stages.guess_check`, which advise mending or leaving out a prior the caller
    gave) said of the constant-velocity prior the sequence passed, the previous step's motion: a departure from it is
    a change of motion (turning back, stopping), right where the step is reliable. ``centroid [3]``: the source's."""
    T = np.asarray(record["transform"], dtype=np.float64)  # [4, 4] T_{i-1}_i
    P = np.asarray(prior, dtype=np.float64)  # [4, 4] the previous step's T_{i-2}_{i-1}
    cos = (np.trace(T[:3, :3].T @ P[:3, :3]) - 1) / 2
    degrees = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    shift = float(np.linalg.norm(T[:3, :3] @ centroid + T[:3, 3] - (P[:3, :3] @ centroid + P[:3, 3])))
    said = {
        FAR_FROM_PRIOR: (f"{FAR_FROM_PRIOR}: this step's motion departs from the previous step's (the "
                         f"--constant-velocity prior) by {degrees:.1f} deg and {shift:.4g} at the source's centroid: "
                         "the motion changed (turning back, stopping), or the step is wrong where it is not reliable"),
        PRIOR_RETURNED: (f"{PRIOR_RETURNED}: this step's pose is the previous step's motion as given (the "
                         "--constant-velocity prior, unrefined with refine: none) and is not reliable"),
    }
    return [said.get(warning.split(":", 1)[0], warning) for warning in record.get("warnings", [])]



def kitti_line(T_0_i: np.ndarray) -> str:
    """The KITTI odometry pose line of ``T_0_i`` ``[4, 4]``: the 3x4 ``[R | t]`` row-major, 12 numbers (as KITTI's
    ``poses/XX.txt``, evo and the KITTI devkit read them)."""
    return " ".join(f"{value:.12e}" for value in np.asarray(T_0_i, dtype=np.float64)[:3].ravel())
