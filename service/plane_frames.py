"""Start rotations from the clouds' dominant plane directions, for scenes built of orthogonal planes.

The normals of a room fragment (floor, walls, tables, cupboards) cluster about three orthogonal directions. Where
each cloud shows such a frame (:func:`plane_frame`: ``F [3, 3]``, its columns the directions), a right rotation maps
the source's frame onto the target's, up to which axis goes where and with which sign: one of the 24 rotations
``F_t G F_s^T``, ``G`` a proper signed permutation (the cube's rotation group), lies within the frames' own error
(a few degrees) of it (:func:`frame_rotations`), where the rotation search's fixed 24 starts lie up to 62.8 degrees
away. :func:`overlap_scores` ranks them by a coarse occupancy correlation, so that only the best few are refined
(``docs/decisions/0021-plane-frame-starts.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.icp import target_normals
from service.rotation_search import search_rotations_for
from service.translation_search import correlation

AXIS_DEGREES = 10.0  # a normal within this angle of a direction (either sign) counts for it
PERPENDICULAR_DEGREES = 20.0  # the second direction is sought among normals within this of perpendicular to the first
MIN_FRAME_SHARE = 0.3  # share of a cloud's points whose normal lies near one of its frame's axes, for a frame
MIN_NORMALS = 10  # defined normals a cloud needs for a frame
OVERLAP_CELLS = 16  # grid cells along the pair's longer extent for overlap_scores
SUPPORT_BLOCK = 64  # rows of the normals' pairwise comparison at a time (support)


def plane_frame(
    points: np.ndarray, normals: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray | None, float]:
    """The dominant plane directions of ``points [N, 3]`` as a rotation ``F [3, 3]`` (columns: the most common normal
    direction, the most common one roughly perpendicular to it, their cross product), and the share of the points
    whose PCA normal (:func:`service.icp.target_normals`; ``normals``, its ``[N, 3]`` normals and ``[N]`` defined
    flags, where the caller has them) lies within ``AXIS_DEGREES`` of one of the three (either sign). ``None, 0``
    where no such pair of directions exists; the frame counts only where the share reaches ``MIN_FRAME_SHARE``
    (:func:`frame_rotations`)."""
    if normals is None:
        normals = target_normals(np.asarray(points, dtype=np.float64))
    normals, defined = normals  # [N, 3], [N]
    n = normals[defined]  # [D, 3] unit, sign arbitrary
    if len(n) < MIN_NORMALS:
        return None, 0.0
    first = int(np.argmax(support(n)))
    d1 = mean_direction(n[alike(n[first : first + 1], n)[0]], n[first])  # [3]
    across = np.flatnonzero(np.abs(n @ d1) < np.sin(np.radians(PERPENDICULAR_DEGREES)))  # [P]
    if len(across) < 3:
        return None, 0.0
    second = across[int(np.argmax(support(n[across])))]
    d2 = mean_direction(n[across[alike(n[second : second + 1], n[across])[0]]], n[second])
    d2 = d2 - (d2 @ d1) * d1
    d2 /= np.linalg.norm(d2)
    frame = np.stack([d1, d2, np.cross(d1, d2)], axis=1)  # [3, 3] columns: the axes, right-handed
    on_axes = np.abs(n @ frame).max(axis=1) > np.cos(np.radians(AXIS_DEGREES))  # [D]
    return frame, float(on_axes.sum()) / len(points)


@dataclass(frozen=True)
class CloudFrame:
    """A cloud's PCA normals and the :func:`plane_frame` they give, found once and shared by the stages that ask."""

    normals: np.ndarray  # [N, 3] unit, sign arbitrary
    defined: np.ndarray  # [N] bool: a plane is defined there
    axes: np.ndarray | None  # [3, 3] columns: the dominant plane directions; None where there are none
    share: float  # of the points, those whose normal lies along one of the axes

    @property
    def counts(self) -> bool:
        """Whether the frame covers at least ``MIN_FRAME_SHARE`` of the points (:func:`frame_rotations` needs it)."""
        return self.axes is not None and self.share >= MIN_FRAME_SHARE

    def turned_back(self, R: np.ndarray) -> CloudFrame:
        """The frame of the cloud's points before they were turned by ``R [3, 3]`` (``p_turned = R @ p``)."""
        return CloudFrame(self.normals @ R, self.defined, None if self.axes is None else R.T @ self.axes, self.share)


def cloud_frame(points: np.ndarray) -> CloudFrame:
    """The :class:`CloudFrame` of ``points [N, 3]``: its :func:`service.icp.target_normals` and :func:`plane_frame`."""
    normals, defined = target_normals(np.asarray(points, dtype=np.float64))  # [N, 3], [N]
    axes, share = plane_frame(points, (normals, defined))
    return CloudFrame(normals, defined, axes, share)


def alike(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``[A, B]`` bool: unit directions ``a [A, 3]`` and ``b [B, 3]`` within ``AXIS_DEGREES`` of each other, either
    sign (the dot products summed axis by axis: faster than a ``[A, 3] @ [3, B]`` matrix product here)."""
    dot = a[:, 0:1] * b[:, 0]
    dot += a[:, 1:2] * b[:, 1]
    dot += a[:, 2:3] * b[:, 2]
    return np.abs(dot, out=dot) > np.cos(np.radians(AXIS_DEGREES))


def support(normals: np.ndarray) -> np.ndarray:
    """``[D]``: for each of ``normals [D, 3]``, how many of them lie within ``AXIS_DEGREES`` of it (itself included),
    in blocks of ``SUPPORT_BLOCK`` rows (a block of the ``[D, D]`` comparison stays in cache: 2.5x faster than the
    whole at ``D`` = 768)."""
    return np.concatenate([np.count_nonzero(alike(normals[i : i + SUPPORT_BLOCK], normals), axis=1)
                           for i in range(0, len(normals), SUPPORT_BLOCK)])


def mean_direction(normals: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The unit mean of ``normals [K, 3]`` after turning each to the side of ``reference [3]``."""
    signs = np.where(normals @ reference < 0, -1.0, 1.0)  # [K]
    mean = (normals * signs[:, None]).mean(axis=0)
    return mean / np.linalg.norm(mean)


def frame_rotations(source: np.ndarray, target: np.ndarray, source_frame: CloudFrame | None = None
                    ) -> np.ndarray | None:
    """``[24, 3, 3]``: the rotations ``F_t G F_s^T`` taking the :func:`plane_frame` of ``source [N, 3]`` onto that of
    ``target [M, 3]`` (``G``: the cube's 24 rotations), or ``None`` unless both clouds have a frame covering at least
    ``MIN_FRAME_SHARE`` of their points. ``source_frame``: the source's :func:`cloud_frame`, where the caller has it."""
    f_s = cloud_frame(source) if source_frame is None else source_frame
    if not f_s.counts:  # most clouds: the target's frame is not needed
        return None
    f_t = cloud_frame(target)
    if not f_t.counts:
        return None
    return f_t.axes[None] @ search_rotations_for(24) @ f_s.axes.T[None]


def overlap_scores(source: np.ndarray, target: np.ndarray, rotations: np.ndarray,
                   cells: int = OVERLAP_CELLS) -> np.ndarray:
    """``[H]``: for each of ``rotations [H, 3, 3]``, the most cells of a coarse grid (``cells`` along the longer
    extent) that the turned ``source [N, 3]`` and ``target [M, 3]`` occupy together at any translation, over the
    fewer cells either occupies alone (1: one cloud's cells all lie in the other's)."""
    scores = np.empty(len(rotations))
    for h, rotation in enumerate(rotations):
        correlated = correlation(source @ rotation.T, target, cells)
        if correlated is None:  # both clouds one point
            scores[h] = 0.0
            continue
        score, _, occupied = correlated
        scores[h] = np.rint(score).max() / max(min(occupied), 1.0)
    return scores
