"""How far a registration result can be trusted: overlap, residual and degenerate geometry.

``reliable`` is a deliberately simple rule: neither cloud is degenerate (all points identical or on one line -- a
rotation about that line cannot be observed) and the share of moved source points with a target point within
``inlier_distance`` reaches both ``RELIABLE_INLIER_RATIO`` and a share of what a right pose reaches: of the
caller's :func:`attainable_on_surface` where it has denser points of the target's surface
(``RELIABLE_RELATIVE_RATIO_ON_SURFACE``), else of what the target's own density allows
(:func:`attainable_inlier_ratio`, ``RELIABLE_RELATIVE_RATIO``). A wrong pose that ICP has pulled onto the target's
surface often still keeps a third of the points near it, but less often half of what a right pose reaches
(``docs/RELIABILITY.md``, "What `reliable` means"). And of the moved source points near the target, the share on it
(:func:`near_surface_share`) reaches ``RELIABLE_NEAR_SHARE_ON_SURFACE`` / ``RELIABLE_NEAR_SHARE`` of that ratio: a
right pose lies on the target where the clouds overlap. Coplanar clouds only earn a warning: their pose is usually
determined, but it can be ambiguous (sliding within the plane, symmetric outlines).

Where the target is smaller than the source (a scan cut to part of what the source sees), a right pose leaves the
source's points beyond the cut far from the target. A caller that knows the target samples its surface densely may
hand :func:`assess` the ratio measured the other way round (:func:`reverse_fit`): where the moved source explains the
target (:func:`explains_the_target`) and the tight fit holds, the inlier-ratio check passes
(``docs/decisions/0084-a-cut-target-the-source-explains.md``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from service.checks import MIN_POINTS
from service.kdtree import KDTree
from service.sampling import distinct_count

POOR_FIT = "poor fit"  # the kind of warning a pose that lays too little of the source on the target gets
LOOSE_FIT = "loose fit"  # the kind of warning a pose near the target but off its surface gets (here and in the stages)
RELIABLE_INLIER_RATIO = 0.3  # lowest inlier ratio of a reliable result (partial overlap is normal)
# ... and at least this share of the target's attainable inlier ratio: 0.6 alone (docs/decisions/0003), 0.5 beside
# the tight-fit condition below, which tells wrong poses apart better; right poses of real scans that overlap by
# half no longer fall below it (docs/decisions/0013-reliable-needs-a-tight-fit.md).
RELIABLE_RELATIVE_RATIO = 0.5
# ... or where the attainable ratio is that of the target's surface (attainable_on_surface), this much of it: range
# images 48 deg apart overlap by about half (docs/decisions/0026-reliable-at-045-of-the-surface-ratio.md)
RELIABLE_RELATIVE_RATIO_ON_SURFACE = 0.45
# ... and with refine="none", the network's pose as it is, this much of either: a raw pose 30-40 deg off kept 0.5-0.6
# of it and passed (docs/decisions/0105-an-unrefined-pose-needs-more-of-the-fit.md)
RELIABLE_RELATIVE_RATIO_UNREFINED = 0.8
NEAR_SURFACE_FACTOR = 3.0  # near_surface_share: points within this many inlier distances count as near the target
# ... and of the moved source points near the target (within NEAR_SURFACE_FACTOR inlier distances), a share within
# one (near_surface_share) of at least this much of the attainable inlier ratio: a right pose lies on the target
# where they overlap, a wrong one pulled onto it often crosses its surface
# (docs/decisions/0013-reliable-needs-a-tight-fit.md).
RELIABLE_NEAR_SHARE = 0.72
# ... and where the attainable ratio is that of the target's surface (attainable_on_surface), this much of it
RELIABLE_NEAR_SHARE_ON_SURFACE = 0.70
# First words of the loose fit measured on the working target (this module's; stages.assess.off_the_surface words the
# entered target's differently: "... of the target's points ...")
WORKING_LOOSE_FIT = (f"{LOOSE_FIT}: of the source points within {NEAR_SURFACE_FACTOR:g} inlier distances of the "
                     "target only")
# Where the caller offers the ratio measured the other way (reverse_fit), the target's points within an inlier distance
# of the moved source must reach RELIABLE_INLIER_RATIO and this share of the source's attainable ratio, and their tight
# fit RELIABLE_NEAR_SHARE_ON_SURFACE of it (docs/decisions/0084-a-cut-target-the-source-explains.md).
RELIABLE_REVERSE_RATIO = 0.6
TARGET_EXPLAINED = "target explained"  # first words of the note on a result whose ratio check passed that way
# Where both clouds' density estimates (attainable_inlier_ratio) are below SCATTERED_DENSITY, hardly a point of
# either has another within the inlier distance: scattered volumes of points, not sampled surfaces (sparse ModelNet40
# samples keep 0.24 and more). There a wrong pose lays as much of the source on the target as a right one, and the
# ratio check judges nothing; such a result is not reliable unless at least SHARED_POINTS_RATIO of the source lands
# on the target's own points, which no wrong pose of points that far apart does: the two clouds share their points
# (docs/decisions/0113-no-reliable-on-scattered-points.md).
SCATTERED_POINTS = "scattered points"
SCATTERED_DENSITY = 0.1
SHARED_POINTS_RATIO = 0.9
DEGENERACY_RATIO = 1e-2  # an axis whose RMS spread is below this fraction of the largest is "flat"
IDENTICAL_TOLERANCE = 1e-9  # largest deviation from the centroid, relative to the coordinates' size

IDENTICAL = "identical"  # first word of each degeneracy warning
COLLINEAR = "collinear"
COPLANAR = "coplanar"
EMPTY = "empty"
FEW = "few distinct points"
_DEGENERATE = (EMPTY, IDENTICAL, FEW, COLLINEAR)  # kinds that make a result unreliable


@dataclass(frozen=True)
class Quality:
    """Quality of a ``src_to_tgt`` pose (distances in the caller's units)."""

    inlier_ratio: float  # fraction of moved source points with a target point within inlier_distance
    residual_rms: float  # RMS of those inlier distances; 0 when there is none
    reliable: bool
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class ReverseFit:
    """How a ``src_to_tgt`` pose's moved source explains the target: the inlier ratio measured the other way round."""

    ratio: float  # share of the target's points with a moved source point within the inlier distance
    near_share: float  # of the target's points within NEAR_SURFACE_FACTOR inlier distances, the share within one
    attainable: float  # the ratio a right pose reaches for the source's sampling (as Quality's, the other way)


def degeneracy_warnings(points: np.ndarray) -> list[str]:
    """Warnings about degenerate geometry of ``points (N, 3)``; empty when the cloud is fine.

    Each warning starts with its kind: ``"empty"``, ``"identical"`` (all points the same), ``"collinear"`` (second
    principal spread below ``DEGENERACY_RATIO`` of the first), ``"few distinct points"`` (fewer than
    ``MIN_POINTS`` distinct coordinates: stacks of repeated points) or ``"coplanar"`` (third principal spread below
    it). At most one kind is reported: the strongest.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points contain NaN or Inf")
    if points.shape[0] == 0:
        return [f"{EMPTY}: the cloud has no points"]
    centred = points - points.mean(axis=0)  # [N, 3]
    magnitude = max(float(np.abs(points).max()), np.finfo(np.float64).tiny)
    if float(np.abs(centred).max()) <= IDENTICAL_TOLERANCE * magnitude:
        return [f"{IDENTICAL}: all its points are the same; no pose can be determined"]  # of a sample: no count
    spread = np.linalg.svd(centred, compute_uv=False) / np.sqrt(points.shape[0])  # [3] RMS per axis
    if spread[1] <= DEGENERACY_RATIO * spread[0]:
        return [
            f"{COLLINEAR}: the points lie on a line (spread ratio {spread[1] / spread[0]:.2g}); "
            "the rotation about that line cannot be determined"
        ]
    distinct = distinct_count(points)
    if distinct < MIN_POINTS:
        return [f"{FEW}: only {distinct} of the {points.shape[0]} points differ (a cloud needs {MIN_POINTS}); "
                "the pose cannot be relied on"]
    if spread[2] <= DEGENERACY_RATIO * spread[0]:
        return [
            f"{COPLANAR}: the points lie in a plane (spread ratio {spread[2] / spread[0]:.2g}); "
            "the pose may be ambiguous (sliding in the plane, symmetric outlines)"
        ]
    return []


def degenerate(points: np.ndarray) -> bool:
    """Whether ``points (N, 3)`` leave a pose undetermined: empty, identical or collinear (see
    :func:`degeneracy_warnings`; coplanar clouds are not degenerate)."""
    return any(w.startswith(_DEGENERATE) for w in degeneracy_warnings(points))


def inlier_statistics(distances: np.ndarray, inlier_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Inlier ratio and inlier RMS residual of nearest-neighbour ``distances (..., N)``.

    A distance at most ``inlier_distance`` is an inlier (``inf``, a missed query, never is).
    Returns ``(...)`` ratios and ``(...)`` RMS residuals over the inliers (0 where there is none).
    """
    distances = np.asarray(distances, dtype=np.float64)
    inlier = distances <= inlier_distance  # [..., N]
    count = inlier.sum(axis=-1)  # [...]
    sq_sum = np.where(inlier, distances, 0.0) ** 2
    rms = np.sqrt(sq_sum.sum(axis=-1) / np.maximum(count, 1))
    return count / max(distances.shape[-1], 1), np.where(count > 0, rms, 0.0)


def near_surface_share(src: np.ndarray, tgt: np.ndarray, R: np.ndarray, t: np.ndarray, inlier_distance: float,
                       tree: KDTree | None = None) -> float:
    """Of the points of ``src (N, 3)`` moved by ``R (3, 3), t (3,)`` that lie within ``NEAR_SURFACE_FACTOR *
    inlier_distance`` of ``tgt (M, 3)``, the share within ``inlier_distance`` (0.0 when none is that near).
    ``tree``: ``KDTree(tgt)`` when the caller has it.

    High for a right pose of a partial view (the source's unseen parts lie far from the target, the rest on it),
    however low its inlier ratio; low for a pose that crosses the target's surface.
    """
    moved = np.asarray(src, dtype=np.float64) @ np.asarray(R).T + t  # [N, 3]
    tree = KDTree(tgt) if tree is None else tree
    dist = tree.query(moved, k=1, distance_upper_bound=NEAR_SURFACE_FACTOR * inlier_distance)[0]  # [N]
    return share_on_surface(dist, inlier_distance)


def share_on_surface(distances: np.ndarray, inlier_distance: float) -> float:
    """Of the nearest-neighbour ``distances (N,)`` at most ``NEAR_SURFACE_FACTOR * inlier_distance``, the share at
    most ``inlier_distance`` (0.0 when there is none)."""
    within = int(np.count_nonzero(distances <= NEAR_SURFACE_FACTOR * inlier_distance))
    return float(np.count_nonzero(distances <= inlier_distance) / within) if within else 0.0


def nearest_other_distances(points: np.ndarray, tree: KDTree | None = None) -> np.ndarray:
    """``[M]`` float64: each of ``points [M, 3]``'s distance to its nearest other point (``M >= 2``). ``tree``:
    ``KDTree(points)`` when the caller has it."""
    points = np.asarray(points, dtype=np.float64)
    return (KDTree(points) if tree is None else tree).query(points, k=2)[0][:, 1]  # [:, 0] is the point itself


def attainable_inlier_ratio(tgt: np.ndarray, inlier_distance: float, tree: KDTree | None = None,
                            nearest_other: np.ndarray | None = None) -> float:
    """Share of the points of ``tgt (M, 3)`` whose nearest other target point lies within ``inlier_distance``.

    About the inlier ratio a right pose reaches when the source samples the same surface independently
    at the target's density: a source point then lies about as far from its nearest target point as
    target points lie from each other. On sparse clouds it is well below 1 (median 0.63 on the 384-point
    test pairs at the quality distance, 0.94 on the 768-point ones), which is why a fixed inlier-ratio
    threshold cannot judge them. 1.0 for fewer than two points. ``tree``: ``KDTree(tgt)`` when the caller has it;
    ``nearest_other``: :func:`nearest_other_distances` of ``tgt`` when the caller has them.
    """
    if len(tgt) < 2:
        return 1.0
    if nearest_other is None:
        nearest_other = nearest_other_distances(tgt, tree)  # [M]
    return float(np.mean(nearest_other <= inlier_distance))


def attainable_on_surface(surface: np.ndarray, tgt: np.ndarray, inlier_distance: float) -> float:
    """Share of the points of ``surface (P, 3)`` -- denser samples of the surface that ``tgt (M, 3)`` samples, e.g.
    the caller's whole target -- that lie within ``inlier_distance`` of a point of ``tgt``, points of ``tgt`` itself
    (distance 0) left out; 1.0 when none is left.

    The inlier ratio a right pose reaches where the clouds overlap: a source point of the overlap lies on the target's
    surface, as these points do. Unlike :func:`attainable_inlier_ratio` it holds where ``tgt``'s points lie farther
    apart than ``inlier_distance`` (a target far larger than the source, which sets the distance): a point on the
    surface then still lies within it of a sample, while no sample has another that near.
    """
    dist = KDTree(tgt).query(np.asarray(surface, dtype=np.float64), k=1)[0]  # [P]
    off_samples = dist[dist > 0]
    return float(np.mean(off_samples <= inlier_distance)) if len(off_samples) else 1.0


def reverse_fit(src: np.ndarray, tgt: np.ndarray, R: np.ndarray, t: np.ndarray, inlier_distance: float,
                attainable: float) -> ReverseFit:
    """The inlier ratio and tight fit of ``tgt (M, 3)``'s points against ``src (N, 3)`` moved by ``R (3, 3), t (3,)``,
    with ``attainable``: the ratio a right pose reaches that way (:func:`attainable_on_surface` of denser samples of
    the source's surface against ``src``, or :func:`attainable_inlier_ratio` of ``src``)."""
    moved = np.asarray(src, dtype=np.float64) @ np.asarray(R, dtype=np.float64).T + t  # [N, 3]
    dist = KDTree(moved).query(np.asarray(tgt, dtype=np.float64), k=1)[0]  # [M]
    return ReverseFit(float(np.mean(dist <= inlier_distance)), share_on_surface(dist, inlier_distance), attainable)


def explains_the_target(fit: ReverseFit) -> bool:
    """Whether the moved source explains the target as a right pose does: ``fit``'s ratio reaches
    ``RELIABLE_INLIER_RATIO`` and ``RELIABLE_REVERSE_RATIO`` of its attainable ratio, and its tight fit
    ``RELIABLE_NEAR_SHARE_ON_SURFACE`` of that ratio."""
    return (fit.ratio >= max(RELIABLE_INLIER_RATIO, RELIABLE_REVERSE_RATIO * fit.attainable)
            and fit.near_share >= RELIABLE_NEAR_SHARE_ON_SURFACE * fit.attainable)


def target_explained(inlier_ratio: float, fit: ReverseFit) -> str:
    """The note on a result whose inlier-ratio check passed because the source explains the target."""
    return (f"{TARGET_EXPLAINED}: the inlier ratio {inlier_ratio:.3f} is below the rule's, but {fit.ratio:.3f} of the "
            f"target lies within the inlier distance of the moved source, >= {RELIABLE_REVERSE_RATIO} of the "
            f"{fit.attainable:.2f} a right pose reaches: the target covers part of the source")


def relative_ratio(on_surface: bool) -> float:
    """The share of the attainable inlier ratio the ``reliable`` rule asks for: ``RELIABLE_RELATIVE_RATIO_ON_SURFACE``
    of the surface estimate (:func:`attainable_on_surface`), else ``RELIABLE_RELATIVE_RATIO`` of the density
    estimate (:func:`attainable_inlier_ratio`)."""
    return RELIABLE_RELATIVE_RATIO_ON_SURFACE if on_surface else RELIABLE_RELATIVE_RATIO


def poor_fit(inlier_ratio: float, attainable: float, on_surface: bool) -> bool:
    """Whether ``inlier_ratio`` is a "poor fit" of the ``reliable`` rule: at least ``RELIABLE_INLIER_RATIO`` (below,
    "low overlap") but under :func:`relative_ratio` of ``attainable`` (the surface estimate where ``on_surface``)."""
    return RELIABLE_INLIER_RATIO <= inlier_ratio < relative_ratio(on_surface) * attainable


def assess(src: np.ndarray, tgt: np.ndarray, R: np.ndarray, t: np.ndarray, inlier_distance: float,
           tree: KDTree | None = None, attainable: float | None = None, on_surface: bool = True,
           reverse: Callable[[], ReverseFit] | None = None, unrefined: bool = False) -> Quality:
    """Quality of the ``src_to_tgt`` pose ``(R (3, 3), t (3,))`` for ``src (N, 3)``, ``tgt (M, 3)``.

    A moved source point ``R p + t`` is an inlier when its nearest target point is at most
    ``inlier_distance`` away (caller's units).  Warnings name the cloud (``"source ..."``,
    ``"target ..."``) and flag a low inlier ratio. ``tree``: ``KDTree(tgt)`` when the caller has it.
    ``attainable``: the inlier ratio a right pose reaches (:func:`attainable_on_surface`) where the caller knows
    it, or with ``on_surface=False`` the :func:`attainable_inlier_ratio` of ``tgt`` the caller already has; else
    this computes the latter. ``reverse``: where the caller knows the target samples its surface densely, the
    :func:`reverse_fit` of this pose, asked only where the inlier ratio alone keeps the result from ``reliable``; if
    the source :func:`explains_the_target` the ratio check passes, with a note instead of its warning.
    ``unrefined``: the pose is the network's, unrefined; a reliable one also keeps ``RELIABLE_RELATIVE_RATIO_UNREFINED``
    of the attainable ratio.
    """
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"R must be (3, 3) and t (3,), got {R.shape} and {t.shape}")
    if not inlier_distance > 0:
        raise ValueError(f"inlier_distance must be positive, got {inlier_distance}")
    src_warnings = degeneracy_warnings(src)
    tgt_warnings = degeneracy_warnings(tgt)
    warnings = [f"source {w}" for w in src_warnings] + [f"target {w}" for w in tgt_warnings]
    degenerate = any(w.startswith(_DEGENERATE) for w in src_warnings + tgt_warnings)

    inlier_ratio, residual_rms, near_share = 0.0, 0.0, 0.0
    on_surface = on_surface and attainable is not None
    near_factor = RELIABLE_NEAR_SHARE_ON_SURFACE if on_surface else RELIABLE_NEAR_SHARE
    relative = relative_ratio(on_surface)
    allows = "a right pose reaches on the target's surface" if on_surface else "the target's density allows"
    if src.shape[0] and tgt.shape[0]:
        tree = KDTree(tgt) if tree is None else tree
        src_in_tgt = src @ R.T + t  # [N, 3]
        dist, _ = tree.query(src_in_tgt, k=1)  # [N]
        ratio, rms = inlier_statistics(dist, inlier_distance)
        inlier_ratio, residual_rms = float(ratio), float(rms)
        if attainable is None:
            attainable = attainable_inlier_ratio(tgt, inlier_distance, tree)
        near_share = share_on_surface(dist, inlier_distance)
    attainable = 1.0 if attainable is None else attainable  # empty clouds: degenerate, never reliable
    ratio_passes = inlier_ratio >= max(RELIABLE_INLIER_RATIO, relative * attainable)
    tight = near_share >= near_factor * attainable
    if not ratio_passes and tight and not degenerate and reverse is not None:
        fit = reverse()
        if explains_the_target(fit):
            ratio_passes = True
            warnings.append(target_explained(inlier_ratio, fit))
    if not ratio_passes and inlier_ratio < RELIABLE_INLIER_RATIO:
        sparse = attainable < RELIABLE_INLIER_RATIO / RELIABLE_RELATIVE_RATIO  # even a right pose keeps little
        warnings.append(f"low overlap: inlier ratio {inlier_ratio:.2f} < {RELIABLE_INLIER_RATIO}" + (
            f" (the target is sparse for the inlier distance: its density allows {attainable:.2f}, so even a right "
            "pose may not reach it)" if sparse else ""))
    elif not ratio_passes:
        warnings.append(f"{POOR_FIT}: inlier ratio {inlier_ratio:.2f} < {relative} of the "
                        f"{attainable:.2f} {allows}")
    elif not tight:
        warnings.append(f"{WORKING_LOOSE_FIT} {near_share:.2f} lie within one, < {near_factor} of the {attainable:.2f} "
                        f"{allows}; a right pose lies on the target where they overlap")
    reliable = not degenerate and ratio_passes and tight
    if (reliable and not on_surface and attainable < SCATTERED_DENSITY and inlier_ratio < SHARED_POINTS_RATIO
            and (source_density := attainable_inlier_ratio(src, inlier_distance)) < SCATTERED_DENSITY):
        warnings.append(f"{SCATTERED_POINTS}: hardly a point of either cloud has another within the inlier distance "
                        f"({source_density:.2f} of the source's, {attainable:.2f} of the target's), as in volumes of "
                        "scattered points rather than sampled surfaces; there a wrong pose lays as much of the source "
                        f"on the target as a right one, and an inlier ratio of {inlier_ratio:.2f} confirms nothing "
                        f"(only {SHARED_POINTS_RATIO}, the source laid on the target's own points, would)")
        reliable = False
    if reliable and unrefined and inlier_ratio < RELIABLE_RELATIVE_RATIO_UNREFINED * attainable:
        warnings.append(f"{POOR_FIT}: the unrefined pose's inlier ratio {inlier_ratio:.2f} < "
                        f"{RELIABLE_RELATIVE_RATIO_UNREFINED} of the {attainable:.2f} {allows}; a refinement "
                        "(refine: icp-plane) settles it or shows it wrong")
        reliable = False
    return Quality(inlier_ratio=inlier_ratio, residual_rms=residual_rms, reliable=reliable, warnings=warnings)
