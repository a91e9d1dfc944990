"""Stage 1b, anchor: each cloud moved to its own centroid before any other stage, the pose moved back after.

Registration does not depend on where the caller's frames lie, but several stages work in the caller's frame: the
translation search turns the source about the frame's origin and grids both clouds together (a source turned about
an origin 100 m away lands far from the target, and the grid's cells grow with the gap), and sampling hashes
coordinates. With both clouds anchored at their own centroids every stage sees clouds about the origin, whatever
the caller's frames (``docs/decisions/0020-clouds-anchored-at-their-centroids.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from service.result import IterationPose, RegistrationResult
from service.stages.validate import Request

ANCHOR_ROWS = 65_536  # at most this many rows, spread through the cloud, are averaged for its anchor
# Where a few points lie far beyond the rest (a glitch at 1e12 in a cloud of metres), their weight drags the mean so far
# from the cloud that, moved to it, the cloud's own points coincide in float64 and its pose is lost. The anchor is then
# the median of MEDIAN_ROWS rows spread through the cloud: where the mean lies more than FAR_FACTOR times their median
# absolute deviation from it (ordinary clouds, skewed or not, stay within a few times it).
MEDIAN_ROWS = 1024
FAR_FACTOR = 1e4


@dataclass(frozen=True)
class Anchors:
    """The points subtracted from each cloud: poses between the anchored clouds <-> the caller's ``src_to_tgt``."""

    source: np.ndarray  # [3] caller's source frame
    target: np.ndarray  # [3] caller's target frame

    def to_anchored(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Caller's ``src_to_tgt`` ``R [3, 3], t [3]`` -> the same motion between the anchored clouds."""
        return R, t + R @ self.source - self.target

    def to_caller(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``src_to_tgt`` between the anchored clouds -> the caller's: ``y - a_t = R (x - a_s) + t``."""
        return R, t + self.target - R @ self.source

    def result_to_caller(self, result: RegistrationResult) -> RegistrationResult:
        """``result`` with its final and per-iteration poses in the caller's frames (nothing else depends on them)."""
        rotation, translation = self.to_caller(result.rotation, result.translation)
        poses = [IterationPose(*self.to_caller(p.rotation, p.translation)) for p in result.iteration_poses]
        return replace(result, rotation=rotation, translation=translation, iteration_poses=poses)


def centroid(points: np.ndarray) -> np.ndarray:
    """``[3]`` mean of at most ``ANCHOR_ROWS`` rows spread evenly through ``points [N, 3]``; their median instead
    where a few far points drag the mean away from the cloud (:data:`FAR_FACTOR`)."""
    stride = max(1, -(-len(points) // ANCHOR_ROWS))  # ceil(N / ANCHOR_ROWS)
    columns = np.ascontiguousarray(points[::stride].T, dtype=np.float64)  # [3, n]: ~10x faster than a mean over rows
    mean = columns.mean(axis=1)  # [3]
    rows = columns[:, :: max(1, columns.shape[1] // MEDIAN_ROWS)]  # [3, <= 2 * MEDIAN_ROWS]
    median = np.median(rows, axis=1)  # [3]
    spread = float(np.median(np.abs(rows - median[:, None]), axis=1).max())  # the widest axis's deviation
    return median if spread > 0 and float(np.abs(mean - median).max()) > FAR_FACTOR * spread else mean


def anchor(request: Request) -> tuple[Request, Anchors]:
    """``request`` with each cloud's :func:`centroid` as its origin (``src_anchor``, ``tgt_anchor``) and the initial
    guess moved with them, and the :class:`Anchors` that take poses back to the caller's frames.

    The clouds themselves are not moved: they are the caller's arrays (:class:`Request`), and a moved copy of two
    2,000,000-point clouds would hold 92 MiB more for the whole request. The sample stage moves the rows it keeps
    (at most ``ENTRY_LIMIT`` per cloud, :mod:`service.reduction`), and every stage after it sees only those.
    """
    anchors = Anchors(centroid(request.src), centroid(request.tgt))
    R_init, t_init = anchors.to_anchored(request.R_init, request.t_init)
    return replace(request, R_init=R_init, t_init=t_init, src_anchor=anchors.source, tgt_anchor=anchors.target), anchors
