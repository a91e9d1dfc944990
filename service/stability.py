"""How firmly the geometry pins a pose down: the point-to-plane information matrix at that pose.

At a registered pose, each source point near the target's surface constrains the motions that would move it
off the tangent plane of its nearest target point. ``H = J^T J / P`` over those pairs (``J``:
:func:`service.icp.plane_jacobian`, rotations about the pairs' centroid with arms in units of the target's RMS
radius, so ``H`` is unitless and independent of the clouds' size and density) says how much the fit changes
for each small motion. Its smallest eigenvalue is the fit's sensitivity to the motion it constrains least
(its eigenvector): near zero when a shape of revolution can turn about its axis, or a flat or elongated overlap
can slide, without leaving the surface. Such a pose is a guess along that motion however well it fits, and on
the sparse test pairs most wrong results that every fit statistic called reliable are of this kind
(``docs/RELIABILITY.md``, "What `reliable` means").

The surface is not the only thing that can pin a motion down: where the two clouds share their sample points
(synthetic pairs, or one scan registered to a copy of itself) the points themselves fix the turn of a shape of
revolution. So a low eigenvalue only counts when moving the paired points by one target sample spacing along the
weak motion leaves their RMS distance to the target within ``PINNED_RATIO`` of what it was: between independent
samples it stays within 0.85-1.11x; between shared points it grows 1.9x or more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.icp import PLANE_MIN_INLIERS, Surface, plane_jacobian, rotation_of, target_normals
from service.kdtree import KDTree
from service.normalization import rms_radius
from service.quality import nearest_other_distances

# A pose whose smallest eigenvalue is below this is weakly constrained (not reliable). Chosen on 300 sparse and
# 170 dense seeded test pairs with `general` + icp-plane (docs/decisions/0003): it flagged 26 of the
# 40 sparse misses, nearly all of which the fit-based rule called reliable, but 8 of 260 right sparse poses and 1 of
# 169 right dense ones.
WEAK_EIGENVALUE = 0.01
# ... and moving the paired points one target sample spacing along the weak motion raises their RMS distance to the
# target by less than this factor (the samples do not pin it either). Between independent samples 0.85-1.11x on the
# sparse and dense test pairs; between the paper protocol's shared points 1.9x and more (same pairs).
PINNED_RATIO = 1.5
ROTATION_SHARE = 0.7  # a weak motion whose eigenvector is at least this much rotation is named a turn
TRANSLATION_SHARE = 0.7  # ... at least this much translation a slide; in between, a turn and slide together
WEAKLY_CONSTRAINED = "weakly constrained"  # the kind of warning of a motion that hardly changes the fit
TURN_ABOUT = "a turn about the axis"  # how the warning names a weak motion that is a turn ...
SLIDE_ALONG = "a slide along"  # ... and one that is a slide
WEAK_TURN = f"{WEAKLY_CONSTRAINED}: {TURN_ABOUT}"  # first words of that warning where the motion is a turn
WEAK_SLIDE = f"{WEAKLY_CONSTRAINED}: {SLIDE_ALONG}"  # ... and where it is a slide


@dataclass(frozen=True)
class Stability:
    """The least constrained motion of a pose (target frame)."""

    eigenvalue: float  # smallest eigenvalue of H (unitless; per pair)
    motion: np.ndarray  # [6] its unit eigenvector: rotation (axis direction) then translation parts
    pairs: int  # source points that entered H
    probe_ratio: float | None = None  # RMS distance after / before a one-spacing move along it (low eigenvalues only)
    centre: np.ndarray | None = None  # [3] the point the rotation part turns about (the pairs' centroid)
    scale: float = 1.0  # the target's RMS radius: the translation part per unit step is ``motion[3:] * scale``
    weak_below: float = WEAK_EIGENVALUE  # the eigenvalue below which the pose counts as weakly constrained
    next_motion: np.ndarray | None = None  # [6] the second least constrained motion
    next_eigenvalue: float = np.inf  # its eigenvalue: the warning names it where it is below weak_below (callers lower)

    @property
    def turn_share(self) -> float:
        """How much of the least constrained motion is rotation (0-1; its squares with the slide's sum to 1)."""
        return float(np.linalg.norm(self.motion[:3]))

    def turn_axis(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A point ``[3]`` on the axis of the least constrained motion's turn and its unit direction ``[3]``: the line
        that motion turns about (its instantaneous screw axis), or ``None`` where it hardly turns."""
        turn, slide = unit_step(self.motion, self.scale)
        norm2 = float(turn @ turn)
        if self.centre is None or norm2 < 1e-12:
            return None
        return self.centre + np.cross(turn, slide) / norm2, turn / np.sqrt(norm2)

    @property
    def weak(self) -> bool:
        """Weakly constrained: neither the surface nor the sample points pin the least constrained motion down."""
        return self.eigenvalue < self.weak_below and (self.probe_ratio is None or self.probe_ratio < PINNED_RATIO)


def unit_step(motion: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The rotation vector ``[3]`` and the translation ``[3]`` of one unit step along ``motion [6]`` (its translation
    part in units of the target's RMS radius ``scale``)."""
    return motion[:3], motion[3:] * scale


def pose_stability(src_in_tgt: np.ndarray, tgt: np.ndarray, tree: KDTree, max_distance: float,
                   surface: Surface | None = None, weak_below: float = WEAK_EIGENVALUE) -> Stability | None:
    """:class:`Stability` of the moved source ``src_in_tgt [N, 3]`` on ``tgt [M, 3]`` (``tree``: its KD-tree), over
    the source points within ``max_distance`` of a target point whose normal is defined.

    ``surface``: the target's normals when the caller has them (the refinement's), else only the normals of the
    target points that are some source point's partner are computed. ``weak_below``: the eigenvalue below which the
    pose is weakly constrained (:attr:`Stability.weak`; the samples are probed below it). None with fewer than
    ``PLANE_MIN_INLIERS`` such points (no rigid motion is determined by them).
    """
    dist, nearest = tree.query(src_in_tgt, k=1, distance_upper_bound=max_distance)  # [N], [N]
    paired = dist < max_distance  # [N]; misses come back as inf
    partners = nearest[paired]  # [Q]
    if surface is not None:
        normals, defined = surface.normals[partners], surface.defined[partners]  # [Q, 3], [Q]
    else:
        needed, where = np.unique(partners, return_inverse=True)
        normals, defined = (x[where] for x in target_normals(tgt, tree=tree, at=needed))
    paired[paired] = defined
    if np.count_nonzero(paired) < PLANE_MIN_INLIERS:
        return None
    p, n = src_in_tgt[paired], normals[defined]  # [P, 3] each
    centre, scale = p.mean(axis=0), rms_radius(tgt)
    J = plane_jacobian(p, n, centre, scale)  # [P, 6]
    eigenvalues, eigenvectors = np.linalg.eigh(J.T @ J / len(p))  # ascending
    eigenvalue, motion = float(max(eigenvalues[0], 0.0)), eigenvectors[:, 0]
    probe = None
    if eigenvalue < weak_below:  # only then does it matter whether the samples pin the motion down
        probe = _probe_ratio(p, dist[paired], tgt, tree, centre, scale, motion)
    return Stability(eigenvalue, motion, len(p), probe, centre, scale, weak_below, eigenvectors[:, 1],
                     float(eigenvalues[1]))


def _probe_ratio(p: np.ndarray, dist: np.ndarray, tgt: np.ndarray, tree: KDTree, centre: np.ndarray,
                 scale: float, motion: np.ndarray) -> float:
    """RMS nearest-target distance of the paired points ``p [P, 3]`` (now ``dist [P]``) after moving them one target
    sample spacing (RMS displacement) along ``motion [6]`` either way, over their RMS distance now (the smaller); 1
    where the motion does not move them (paired points that coincide: nothing pins the motion)."""
    spacing = float(np.median(nearest_other_distances(tgt, tree)))  # the target's median sample spacing
    turn, slide = unit_step(motion, scale)  # [3], [3]
    displacement = np.cross(turn, p - centre) + slide  # [P, 3] linearised, per unit step
    moves = float(np.sqrt(np.mean(np.sum(displacement**2, axis=1))))  # RMS displacement per unit step
    if not moves > 1e-12 * max(scale, spacing):  # the motion does not move the points (they coincide): no probe
        return 1.0
    step = spacing / moves
    before = max(float(np.sqrt(np.mean(dist**2))), np.finfo(np.float64).tiny)
    ratios = []
    for sign in (1.0, -1.0):
        rotvec = sign * step * turn
        moved = (p - centre) @ rotation_of(rotvec, float(np.linalg.norm(rotvec))).T + centre + sign * step * slide
        after, _ = tree.query(moved, k=1)  # [P]
        ratios.append(float(np.sqrt(np.mean(after**2))) / before)
    return min(ratios)


def weak_motion_warning(stability: Stability | None) -> str | None:
    """The warning of a weakly constrained pose, naming its least constrained motion, and its second where that one is
    below the same bar (a pipe's slide along its axis and turn about it); None otherwise."""
    if stability is None or not stability.weak:
        return None
    what, why = _motion_words(stability.motion)
    also = ""
    if stability.next_motion is not None and stability.next_eigenvalue < stability.weak_below:  # a pipe: slide, turn
        also = f"; {_motion_words(stability.next_motion)[0]} hardly changes it either"
    return (f"{WEAKLY_CONSTRAINED}: {what} hardly changes the fit (stability {stability.eigenvalue:.2g} < "
            f"{stability.weak_below:g}); {why}, and the pose along it is a guess{also}")


def _motion_words(motion: np.ndarray) -> tuple[str, str]:
    """What the unit motion ``[6]`` (rotation part, then translation part) is, in words, and why a shape allows it."""
    turn, slide = motion[:3], motion[3:]
    turn_share, slide_share = float(np.linalg.norm(turn)), float(np.linalg.norm(slide))  # their squares sum to 1
    axis, direction = turn / max(turn_share, 1e-12), slide / max(slide_share, 1e-12)
    if turn_share >= ROTATION_SHARE:
        return f"{TURN_ABOUT} ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f})", "the shape may be symmetric about it"
    if slide_share >= TRANSLATION_SHARE:
        return (f"{SLIDE_ALONG} ({direction[0]:.2f}, {direction[1]:.2f}, {direction[2]:.2f})",
                "the overlap may be flat or elongated along it")
    return f"a turn about ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}) with a slide", "the overlap may be symmetric"
