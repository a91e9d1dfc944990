"""Point-to-point ICP refinement of a ``src_to_tgt`` pose (numpy + :class:`service.kdtree.KDTree`).

Each iteration moves the source with the current pose, pairs every moved point with its nearest
target point, keeps the pairs closer than ``max_distance`` and solves the increment with the
project's one weighted Procrustes (:func:`service.procrustes.weighted_procrustes`, uniform weights,
weighted centroid).  With that truncation the cost ``sum_i min(d_i^2, max_distance^2)`` never
increases from one iteration to the next.

With partial overlap, source points outside the overlap still find a (wrong) target point near the
edge of the overlap and pull the pose by a fraction of the point spacing (a few tenths of a degree
on 768-point partial views).  ``reciprocal=True`` (the default) keeps only mutual nearest
neighbours, which removes those pairs: two views sharing their points in the overlap then align
exactly.  It costs one more nearest-neighbour query per iteration, and the monotone-cost guarantee
above only holds for ``reciprocal=False`` (plain point-to-point ICP).

:func:`icp_plane` is point-to-plane ICP: it minimises the distances of the moved source points to the
tangent planes of their nearest target points (normals by PCA of each target point's neighbourhood).
Between two independent samplings of one surface no point has an exact partner, and point-to-point
ICP converges to a pose biased by the sampling (a few degrees on sparse clouds); sliding along the
tangent plane costs nothing in the point-to-plane objective, so it converges much closer
(``docs/DESIGN.md``, "Refinement").

:func:`refine_plane` (``refine="icp-plane"``) puts a wide-basin stage in front of it:
:func:`icp_symmetric` pairs without the mutual check at ``WIDE_DISTANCE_FACTOR`` times the distance,
measures each residual along the sum of both points' normals (the symmetric point-to-plane objective)
and weights it with a Geman-McClure kernel, so far-off pairs pull little but still pull. It reaches
the right basin from starts that plain point-to-plane ICP leaves in a wrong one (sparse independent
samples: 0.78 -> 0.85 of pairs within 5 deg; ``docs/ACCURACY.md``); the reciprocal point-to-plane
stage then gives back the precision the wide stage lacks on partial overlaps.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from service import normalization
from service.distinct_neighbours import DistinctPoints, copied_neighbourhoods
from service.kdtree import KDTree
from service.procrustes import compose, weighted_procrustes

MIN_INLIERS = 3  # fewer pairs than this cannot fix a rigid pose: the pose is left as it is
PLANE_MIN_INLIERS = 6  # point-to-plane: one equation per pair, six unknowns
NORMAL_NEIGHBOURS = 12  # target points (itself included) whose PCA gives a target point's normal
NORMAL_MIN_SPREAD = 1e-2  # a neighbourhood whose 2nd principal variance is below this fraction of the 1st
# is (nearly) a line: its normal is undefined and the point takes no part in point-to-plane ICP
WIDE_DISTANCE_FACTOR = 3.0  # refine_plane: the wide stage pairs points up to this many times max_distance
WIDE_TOLERANCE = 1e-4  # refine_plane: the wide stage stops on updates below this (rad, x RMS radius)
PLANE_MIN_EIGEN_RATIO = 1e-4  # smallest / largest eigenvalue of the scaled 6x6 normal equations below this:
# some motion (sliding on a plane, turning about an axis of symmetry) is not observed, no update is made


@dataclass(frozen=True)
class IcpResult:
    """Refined ``src_to_tgt`` pose and how well it fits, measured at that pose."""

    rotation: np.ndarray  # [3, 3] float64, det +1
    translation: np.ndarray  # [3] float64, caller's units
    iterations: int  # Procrustes updates applied
    inlier_ratio: float  # fraction of source points with a target point closer than max_distance
    residual_rms: float  # RMS distance of those pairs (0 when there is none)
    converged: bool = True  # False: the refinement stopped on a degenerate system (see ``warnings``)
    warnings: tuple[str, ...] = ()  # why the refinement stopped early, for the caller's warnings


def icp(
    src: np.ndarray,
    tgt: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    max_distance: float,
    max_iterations: int = 30,
    tolerance: float = 1e-6,
    reciprocal: bool = True,
) -> IcpResult:
    """Refine ``(R0, t0)`` so that ``R src + t`` lies on ``tgt``.

    Args:
        src: ``(N, 3)`` source points.
        tgt: ``(M, 3)`` target points.
        R0: ``(3, 3)`` initial ``src_to_tgt`` rotation.
        t0: ``(3,)`` initial ``src_to_tgt`` translation.
        max_distance: pairs at this distance or farther are ignored (caller's units, > 0).
        max_iterations: most Procrustes updates.
        tolerance: stop once an update rotates by less than ``tolerance`` radians and translates by
            less than ``tolerance`` times the target's RMS radius.
        reciprocal: keep a pair only when the source point is also the target point's nearest
            source point (mutual nearest neighbours); ``False`` gives plain point-to-point ICP.

    Returns:
        :class:`IcpResult`; with fewer than ``MIN_INLIERS`` pairs the pose is kept from there on,
        ``converged`` is False and ``warnings`` says so (as :func:`icp_plane`'s).  Its
        ``inlier_ratio`` and ``residual_rms`` use the distance rule only (as
        :func:`service.quality.assess` does), whatever ``reciprocal`` is.

    Raises:
        ValueError: on wrongly shaped inputs or a non-positive ``max_distance``.
    """
    src, tgt, R, t = _checked(src, tgt, R0, t0, max_distance, max_iterations)
    tree = KDTree(tgt)
    src_tree = KDTree(src) if reciprocal else None
    translation_tolerance = tolerance * rms_radius(tgt)
    iterations, warnings = 0, []
    for _ in range(max_iterations):
        src_in_tgt = src @ R.T + t  # [N, 3]
        inlier, nearest = _pairs(tree, src_tree, src_in_tgt, tgt, R, t, max_distance)  # [N], [N]
        if np.count_nonzero(inlier) < MIN_INLIERS:
            warnings.append(f"refinement: point-to-point ICP found {np.count_nonzero(inlier)} pairs closer than "
                            f"{max_distance:.3g} (needs {MIN_INLIERS}); kept the pose after {iterations} updates")
            break
        R_step, t_step = weighted_procrustes(src_in_tgt[inlier], tgt[nearest[inlier]], None, "weighted")
        R, t = compose(R_step, t_step, R, t)
        iterations += 1
        angle = np.linalg.norm(R_step - np.eye(3)) / np.sqrt(2.0)  # ~ rotation angle when small
        if angle < tolerance and np.linalg.norm(t_step) < translation_tolerance:
            break
    return _result(tree, src, R, t, iterations, max_distance, tuple(warnings))


def icp_many(
    src: np.ndarray,
    tgt: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    max_distance: float,
    max_iterations: int = 30,
    tolerance: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Plain point-to-point :func:`icp` (``reciprocal=False``) of one source from ``H`` starts at once.

    ``R0 [H, 3, 3]``, ``t0 [H, 3]`` -> refined ``R [H, 3, 3]``, ``t [H, 3]``. Each start takes the updates
    :func:`icp` would give it (equal to rounding): per iteration one KD-tree query for the moved
    source of every start still running and one batched Procrustes whose weights are the pairs'
    masks; a start stops on its own when its update is below ``tolerance`` or it has fewer than
    ``MIN_INLIERS`` pairs. The rotation search refines its 24 or 60 hypotheses with it.
    """
    R0, t0 = np.asarray(R0, dtype=np.float64), np.asarray(t0, dtype=np.float64)
    if R0.ndim != 3 or R0.shape[1:] != (3, 3) or t0.shape != (len(R0), 3):
        raise ValueError(f"R0 must be (H, 3, 3) and t0 (H, 3), got {R0.shape} and {t0.shape}")
    src, tgt, _, _ = _checked(src, tgt, np.eye(3), np.zeros(3), max_distance, max_iterations)
    tree = KDTree(tgt)
    translation_tolerance = tolerance * rms_radius(tgt)
    R, t = R0.copy(), t0.copy()
    running = np.arange(len(R))  # starts still updating
    for _ in range(max_iterations):
        if running.size == 0:
            break
        moved = src @ R[running].transpose(0, 2, 1) + t[running, None]  # [A, N, 3]
        dist, nearest = tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=max_distance)
        inlier = (dist < max_distance).reshape(moved.shape[:2])  # [A, N]
        enough = np.count_nonzero(inlier, axis=1) >= MIN_INLIERS  # [A]
        partner = tgt[np.minimum(nearest, len(tgt) - 1)].reshape(moved.shape)  # [A, N, 3]; misses weigh 0
        R_step, t_step = weighted_procrustes(moved[enough], partner[enough], inlier[enough].astype(np.float64))
        updated = running[enough]
        R[updated], t[updated] = compose(R_step, t_step, R[updated], t[updated])
        angle = np.linalg.norm(R_step - np.eye(3), axis=(1, 2)) / np.sqrt(2.0)  # [U]
        still = (angle >= tolerance) | (np.linalg.norm(t_step, axis=1) >= translation_tolerance)
        running = updated[still]
    return R, t


def target_normals(tgt: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS, tree: KDTree | None = None,
                   at: np.ndarray | None = None, nearest_rows: np.ndarray | None = None,
                   distinct: DistinctPoints | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of ``tgt (M, 3)`` by PCA of each point's ``neighbours`` nearest points (itself included), each
    place counted once: a neighbourhood that holds copies of a point takes its neighbours from the distinct points
    (:mod:`service.distinct_neighbours`).

    Returns ``normals (M, 3)`` (sign arbitrary: the point-to-plane residual is squared) and ``defined (M,)``:
    False where the neighbourhood is (nearly) a line or a single point, so that no plane is defined.
    ``at (A,)``: only the normals of ``tgt[at]`` (``(A, 3)`` and ``(A,)``). ``nearest_rows (M, K)``: each point's
    nearest rows, nearest first, ``K >= neighbours``, when the caller has them (no query then, and no search for
    copies: a farthest-point sample holds none). ``distinct``: ``DistinctPoints(tgt)`` where the caller keeps one.
    """
    points = tgt if at is None else tgt[at]  # [A, 3]
    k = min(int(neighbours), tgt.shape[0])
    if k < 3:
        return np.zeros_like(points), np.zeros(points.shape[0], dtype=bool)
    if nearest_rows is not None and at is None and len(nearest_rows) == len(tgt) and nearest_rows.shape[1] >= k:
        hood = tgt[nearest_rows[:, :k]]  # [M, k, 3]
    else:
        tree = KDTree(tgt) if tree is None else tree
        dist, idx = tree.query(points, k=k)  # [A, k]
        hood = tgt[idx]  # [A, k, 3]
        copied = copied_neighbourhoods(dist, hood)  # [A]
        if copied.any():
            apart = (DistinctPoints(tgt) if distinct is None else distinct).neighbourhoods(points[copied], k)
            if apart is not None:
                hood[copied] = apart
    centred = hood - hood.mean(axis=1, keepdims=True)  # [A, k, 3]
    cov = centred.transpose(0, 2, 1) @ centred / k  # [A, 3, 3] (batched matmul: 3x faster than einsum here)
    variance, normals = smallest_eigenvectors(cov)  # [A, 3] ascending, [A, 3]
    defined = variance[:, 1] > NORMAL_MIN_SPREAD**2 * variance[:, 2]  # [A]; 0 > 0 is False too
    return normals, defined


def smallest_eigenvectors(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues ``[M, 3]`` (ascending) of symmetric ``cov [M, 3, 3]`` and the unit eigenvector ``[M, 3]`` of
    the smallest, in closed form (~5x faster than ``np.linalg.eigh`` on 768 matrices; equal to 1e-15).

    Eigenvalues by the trigonometric solution of the characteristic cubic; the eigenvector as the longest cross
    product of two rows of ``cov - lowest * I``. Where that cross product vanishes (two or three equal
    eigenvalues: the smallest one's eigenvector is not unique) ``np.linalg.eigh`` decides, as before.
    """
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]  # [M] each
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    mean = (a00 + a11 + a22) / 3.0
    d0, d1, d2 = a00 - mean, a11 - mean, a22 - mean
    spread = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    s = np.where(spread > 0, spread, 1.0)
    b00, b11, b22, b01, b02, b12 = d0 / s, d1 / s, d2 / s, a01 / s, a02 / s, a12 / s  # (cov - mean I) / spread
    half_det = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)) / 2
    angle = np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0
    high = mean + 2.0 * spread * np.cos(angle)
    low = mean + 2.0 * spread * np.cos(angle + 2.0 * np.pi / 3.0)
    values = np.stack([low, 3.0 * mean - high - low, high], axis=1)  # [M, 3]
    r0 = np.stack([a00 - low, a01, a02], axis=1)  # [M, 3]: rows of cov - low I
    r1 = np.stack([a01, a11 - low, a12], axis=1)
    r2 = np.stack([a02, a12, a22 - low], axis=1)
    crosses = np.stack([cross(r0, r1), cross(r0, r2), cross(r1, r2)], axis=1)  # [M, 3, 3]
    lengths = np.einsum("mcj,mcj->mc", crosses, crosses)  # [M, 3] squared
    pick = lengths.argmax(axis=1)  # [M]
    rows = np.arange(len(cov))
    longest = lengths[rows, pick]  # [M]
    vectors = crosses[rows, pick] / np.sqrt(np.maximum(longest, np.finfo(np.float64).tiny))[:, None]  # [M, 3]
    # |cross| ~ (middle - low)(high - low): tiny against high^2 when the lowest eigenvalue is (nearly) repeated
    unsure = ~(np.sqrt(longest) > 1e-8 * high * high)
    if unsure.any():
        values[unsure], axes = np.linalg.eigh(cov[unsure])
        vectors[unsure] = axes[:, :, 0]
    return values, vectors


@dataclass(frozen=True)
class Surface:
    """A cloud's KD-tree and PCA normals (:func:`target_normals`), built once and shared by both
    stages of :func:`refine_plane`."""

    tree: KDTree
    normals: np.ndarray  # [M, 3] unit, sign arbitrary
    defined: np.ndarray  # [M] bool

    @classmethod
    def of(cls, points: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS, nearest_rows: np.ndarray | None = None
           ) -> Surface:
        """``nearest_rows [M, K]``: the points' nearest rows where the caller has them (:func:`target_normals`)."""
        tree = KDTree(points)
        return cls(tree, *target_normals(points, neighbours, tree, nearest_rows=nearest_rows))

    def at(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The normals ``[R, 3]`` and ``defined [R]`` of the points ``rows [R]``."""
        return self.normals[rows], self.defined[rows]


class LazySurface:
    """A cloud's KD-tree, with each point's PCA normal (:func:`target_normals`) computed when a caller first reads it:
    for a dense cloud of which a refinement pairs only a few thousand points."""

    def __init__(self, points: np.ndarray, tree: KDTree, neighbours: int = NORMAL_NEIGHBOURS) -> None:
        self.points, self.tree, self.neighbours = points, tree, neighbours  # [M, 3] float64, its tree
        self.distinct = DistinctPoints(points)  # hashed only where a neighbourhood holds copies
        self.normals = np.zeros((len(points), 3))  # [M, 3] those computed so far
        self.defined = np.zeros(len(points), dtype=bool)  # [M]
        self.known = np.zeros(len(points), dtype=bool)  # [M] whose normal is computed

    def at(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The normals ``[R, 3]`` and ``defined [R]`` of the points ``rows [R]``, computing those not yet known."""
        missing = np.unique(rows[~self.known[rows]])  # [U]
        if missing.size:
            self.normals[missing], self.defined[missing] = target_normals(self.points, self.neighbours, self.tree,
                                                                          at=missing, distinct=self.distinct)
            self.known[missing] = True
        return self.normals[rows], self.defined[rows]


def icp_symmetric(
    src: np.ndarray,
    tgt: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    max_distance: float,
    max_iterations: int = 30,
    tolerance: float = WIDE_TOLERANCE,
    normal_neighbours: int = NORMAL_NEIGHBOURS,
    target_surface: Surface | None = None,
    source_surface: Surface | None = None,
) -> IcpResult:
    """Robust symmetric point-to-plane ICP: a wide basin for a start some way off the answer.

    Each iteration pairs every moved source point with its nearest target point closer than
    ``max_distance`` (no mutual check), takes the residual along ``n = n_t + R n_s`` (both points'
    normals, signs aligned; the target's alone where the source's is undefined) and solves the same
    linearised 6-DoF step as :func:`icp_plane` with Geman-McClure weights ``(s^2 / (s^2 + r^2))^2``,
    ``s = max_distance / 3``. Pairs need a defined target normal. ``target_surface`` / ``source_surface``:
    ``Surface.of(tgt)`` / ``Surface.of(src)`` when the caller has them (the source's normals, in its own frame,
    do not change with the pose).

    Returns:
        :class:`IcpResult` (statistics at ``max_distance``, as :func:`icp`). With fewer than
        ``PLANE_MIN_INLIERS`` pairs or a degenerate system it stops, keeps the last pose and says why in
        ``warnings``.
    """
    src, tgt, R, t = _checked(src, tgt, R0, t0, max_distance, max_iterations)
    surface = Surface.of(tgt, normal_neighbours) if target_surface is None else target_surface
    tree, tgt_normals, tgt_defined = surface.tree, surface.normals, surface.defined  # [M, 3], [M]
    own = Surface.of(src, normal_neighbours) if source_surface is None else source_surface
    src_normals, src_defined = own.normals, own.defined  # [N, 3], [N] in the source frame
    scale, sigma2 = rms_radius(tgt), (max_distance / 3.0) ** 2
    iterations, warnings = 0, []
    for _ in range(max_iterations):
        src_in_tgt = src @ R.T + t  # [N, 3]
        dist, nearest = tree.query(src_in_tgt, k=1, distance_upper_bound=max_distance)  # [N], [N]
        pair = dist < max_distance
        pair[pair] = tgt_defined[nearest[pair]]
        if np.count_nonzero(pair) < PLANE_MIN_INLIERS:
            warnings.append(f"refinement: wide-basin ICP found {np.count_nonzero(pair)} pairs closer than "
                            f"{max_distance:.3g}; kept the pose after {iterations} updates")
            break
        p, q, n_t = src_in_tgt[pair], tgt[nearest[pair]], tgt_normals[nearest[pair]]  # [P, 3] each
        n_s = src_normals[pair] @ R.T  # [P, 3] source normals in the target frame
        n_s *= np.where(np.einsum("pc,pc->p", n_s, n_t) < 0, -1.0, 1.0)[:, None]
        n = np.where(src_defined[pair, None], n_s + n_t, n_t)  # [P, 3]
        n /= np.linalg.norm(n, axis=1, keepdims=True)  # |n_s + n_t| >= sqrt(2) after the sign flip
        r = np.einsum("pc,pc->p", n, p - q)  # [P] signed residuals
        w = (sigma2 / (sigma2 + r * r)) ** 2  # [P] Geman-McClure weights
        step = _plane_step(p, n, r, w, scale)
        if isinstance(step, float):
            warnings.append(f"refinement: wide-basin ICP stopped on a degenerate system (eigenvalue ratio {step:.1e}) "
                            f"after {iterations} updates")
            break
        R_step, t_step, rotated, moved = step
        R, t = compose(R_step, t_step, R, t)
        iterations += 1
        if rotated < tolerance and moved < tolerance * scale:
            break
    return _result(tree, src, R, t, iterations, max_distance, tuple(warnings))


def refine_plane(
    src: np.ndarray,
    tgt: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    max_distance: float,
    max_iterations: int = 30,
    tolerance: float = 1e-5,
    target_surface: Surface | None = None,
    source_surface: Surface | None = None,
) -> IcpResult:
    """``refine="icp-plane"``: :func:`icp_symmetric` at ``WIDE_DISTANCE_FACTOR * max_distance`` (to reach
    the right basin), then reciprocal :func:`icp_plane` at ``max_distance`` (precision); each stage runs
    at most ``max_iterations`` updates; ``tolerance`` is the precise stage's (1e-5 rad: 1e-6 moved no pose of the
    170 dense test pairs by more than 1e-5 deg).

    ``target_surface`` / ``source_surface``: ``Surface.of(tgt)`` / ``Surface.of(src)`` when the caller has them
    (one registration refines many starts of the same clouds).
    Returns the second stage's :class:`IcpResult` with ``iterations`` counting both stages (the wide
    stage's own warnings are dropped: the precise stage meets the same geometry and reports it).
    """
    src, tgt, R0, t0 = _checked(src, tgt, R0, t0, max_distance, max_iterations)  # before building the tree
    surface = Surface.of(tgt) if target_surface is None else target_surface
    wide = icp_symmetric(src, tgt, R0, t0, max_distance=WIDE_DISTANCE_FACTOR * max_distance,
                         max_iterations=max_iterations, target_surface=surface, source_surface=source_surface)
    precise = icp_plane(src, tgt, wide.rotation, wide.translation, max_distance=max_distance,
                        max_iterations=max_iterations, tolerance=tolerance, target_surface=surface,
                        source_surface=source_surface)
    return dataclasses.replace(precise, iterations=wide.iterations + precise.iterations)


def icp_plane(
    src: np.ndarray,
    tgt: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    max_distance: float,
    max_iterations: int = 30,
    tolerance: float = 1e-6,
    reciprocal: bool = True,
    normal_neighbours: int = NORMAL_NEIGHBOURS,
    target_surface: Surface | LazySurface | None = None,
    source_surface: Surface | None = None,
    point_fallback: bool = True,
    scale: float | None = None,
) -> IcpResult:
    """Refine ``(R0, t0)`` with point-to-plane ICP: minimise ``sum_i (n_i . (R src_i + t - tgt_j(i)))^2``.

    Target normals come from :func:`target_normals` (once per call).  Each iteration pairs every moved
    source point with its nearest target point, keeps pairs closer than ``max_distance`` (mutual
    nearest neighbours when ``reciprocal``) whose target normal is defined, and solves the
    linearised 6-DoF least squares (small rotation ``w`` about the pairs' centroid, translation)
    through its 6x6 normal equations, scaled by ``scale`` (default: the target's RMS radius) so the test below
    does not depend on units; the update applies the exact rotation of ``w`` (Rodrigues).

    Args:
        src, tgt, R0, t0, max_distance, max_iterations, tolerance, reciprocal: as :func:`icp`.
        normal_neighbours: neighbourhood size of the target normals.
        target_surface: ``Surface.of(tgt, normal_neighbours)`` (or a :class:`LazySurface` of ``tgt``) when the
            caller has it.
        source_surface: ``Surface.of(src)`` when the caller has it (only its KD-tree is used, for the mutual check).
        point_fallback: on a degenerate system, continue with point-to-point :func:`icp`; ``False``: stop there (for
            a caller that takes no pose from a refinement that warns).
        scale: the length that scales the normal equations and the translation ``tolerance``: the extent of the
            surface the pairs can cover, where the target reaches far beyond it (one far point, a background).

    Returns:
        :class:`IcpResult`.  With fewer than ``PLANE_MIN_INLIERS`` usable pairs, or normal equations
        whose smallest eigenvalue is below ``PLANE_MIN_EIGEN_RATIO`` of the largest (a planar,
        linear or symmetric target leaves some motion unobserved), the pose of the last good
        iteration is kept, ``converged`` is False and ``warnings`` says why -- except for a degenerate
        system with ``point_fallback``, where point-to-point :func:`icp` continues from that pose (``converged`` is
        then its own).
        ``inlier_ratio`` and ``residual_rms`` are point-to-point distances, as for :func:`icp`.

    Raises:
        ValueError: on wrongly shaped inputs or a non-positive ``max_distance``.
    """
    src, tgt, R, t = _checked(src, tgt, R0, t0, max_distance, max_iterations)
    surface = Surface.of(tgt, normal_neighbours) if target_surface is None else target_surface
    tree = surface.tree
    src_tree = None if not reciprocal else KDTree(src) if source_surface is None else source_surface.tree
    scale = rms_radius(tgt) if scale is None else scale
    iterations, warnings, history = 0, [], PairingHistory()
    for _ in range(max_iterations):
        src_in_tgt = src @ R.T + t  # [N, 3]
        inlier, nearest = _pairs(tree, src_tree, src_in_tgt, tgt, R, t, max_distance)  # [N], [N]
        normals, defined = surface.at(nearest[inlier])  # [C, 3], [C] of the paired target points
        inlier[inlier] = defined
        normals = normals[defined]  # [K, 3]
        if history.recurred(inlier, nearest):
            break  # a limit cycle: further updates only alternate between the same poses
        count = int(np.count_nonzero(inlier))
        if count < PLANE_MIN_INLIERS:
            warnings.append(
                f"refinement: point-to-plane ICP found {count} pairs closer than {max_distance:.3g} with a "
                f"defined target normal (needs {PLANE_MIN_INLIERS}); kept the pose after {iterations} updates"
            )
            break
        p, q, n = src_in_tgt[inlier], tgt[nearest[inlier]], normals  # [K, 3] each
        step = _plane_step(p, n, np.einsum("kc,kc->k", n, p - q), None, scale)
        if isinstance(step, float):
            warnings.append(
                "refinement: point-to-plane ICP stopped on a degenerate system (the target's normals leave a "
                f"motion unobserved: eigenvalue ratio {step:.1e} < {PLANE_MIN_EIGEN_RATIO:.0e}; planar, linear or "
                f"symmetric surface) after {iterations} updates"
                + ("; continued with point-to-point ICP, which can still use a planar target's outline"
                   if point_fallback else "")
            )
            if not point_fallback:
                break
            fallback = icp(src, tgt, R, t, max_distance=max_distance, max_iterations=max_iterations - iterations,
                           tolerance=tolerance, reciprocal=reciprocal)
            return dataclasses.replace(fallback, iterations=iterations + fallback.iterations,
                                       warnings=(*warnings, *fallback.warnings))
        R_step, t_step, rotated, moved = step
        R, t = compose(R_step, t_step, R, t)
        iterations += 1
        if rotated < tolerance and moved < tolerance * scale:
            break
    return _result(tree, src, R, t, iterations, max_distance, tuple(warnings))


def _plane_step(p: np.ndarray, n: np.ndarray, r: np.ndarray, w: np.ndarray | None, scale: float):
    """The (weighted) least-squares rigid step that moves ``p [P, 3]`` along normals ``n [P, 3]`` to cancel the
    residuals ``r = n . (p - q) [P]`` (linearised about the pairs' centroid; the exact rotation of the solved
    axis-angle), with the 6x6 normal equations scaled by ``scale`` so the degeneracy test is unitless.

    Returns ``(R_step [3, 3], t_step [3], rotation angle, translation length)``, or the eigenvalue ratio (a
    float) when the smallest eigenvalue is below ``PLANE_MIN_EIGEN_RATIO`` of the largest (some motion is not
    observed).
    """
    centre = p.mean(axis=0) if w is None else (w @ p) / w.sum()  # [3]
    J = plane_jacobian(p, n, centre, scale)  # [P, 6]
    Jw = J if w is None else J * w[:, None]  # [P, 6]
    H, g = Jw.T @ J, -(Jw.T @ r) / scale  # [6, 6], [6]
    eigenvalues, eigenvectors = np.linalg.eigh(H)  # ascending
    if not eigenvalues[0] > PLANE_MIN_EIGEN_RATIO * eigenvalues[-1]:
        return max(eigenvalues[0], 0.0) / max(eigenvalues[-1], 1e-300)
    x = eigenvectors @ ((eigenvectors.T @ g) / eigenvalues)  # [6] = H^-1 g
    rotvec, tau = x[:3], x[3:] * scale  # rotation vector about ``centre``, translation of ``centre``
    angle = float(np.sqrt(rotvec @ rotvec))
    R_step = rotation_of(rotvec, angle)
    t_step = centre + tau - R_step @ centre  # p -> centre + R_step (p - centre) + tau
    return R_step, t_step, angle, float(np.sqrt(tau @ tau))


def plane_jacobian(p: np.ndarray, n: np.ndarray, centre: np.ndarray, scale: float) -> np.ndarray:
    """``[..., P, 6]`` derivatives of the point-to-plane residuals ``n . (p - q)`` of points ``p [..., P, 3]`` with
    normals ``n [..., P, 3]`` with respect to a small rotation about ``centre [..., 3]`` and a translation over
    ``scale``: rows ``[arm x n, n]`` with ``arm = (p - centre) / scale`` (unitless); leading axes are a batch."""
    arm = (p - centre[..., None, :]) / scale  # [..., P, 3]
    J = np.empty((*p.shape[:-1], 6))  # [..., P, 6]
    J[..., :3] = cross(arm, n)
    J[..., 3:] = n
    return J


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of ``[..., 3]`` arrays: the same products and differences, so equal to the bit, without its axis
    handling, which costs more than the arithmetic on the refinement's small arrays."""
    a0, a1, a2, b0, b1, b2 = a[..., 0], a[..., 1], a[..., 2], b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def rotation_of(rotvec: np.ndarray, angle: float) -> np.ndarray:
    """The rotation matrix ``[3, 3]`` of the axis-angle vector ``rotvec [3]`` of norm ``angle`` (Rodrigues;
    second-order series below 1e-8 rad, where the closed form loses digits)."""
    x, y, z = rotvec
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])  # [3, 3] cross-product matrix
    if angle < 1e-8:
        return np.eye(3) + K + 0.5 * (K @ K)
    return np.eye(3) + (np.sin(angle) / angle) * K + ((1.0 - np.cos(angle)) / angle**2) * (K @ K)


class PairingHistory:
    """Spots an ICP limit cycle: the pairs of an earlier update come back after different ones.

    With the same pairs the solve lands (to within the linearisation) on the same pose again, so the
    pose only alternates between the minima of the recurring pairings (steps of 1e-5 to 6e-4 rad on
    the dense test pairs, until the update cap); the loop can stop at once.
    """

    def __init__(self) -> None:
        self.seen: set[int] = set()
        self.last: int | None = None

    def recurred(self, inlier: np.ndarray, nearest: np.ndarray) -> bool:
        """Record this update's pairs (``inlier [N]`` bool, ``nearest [N]``); True if they close a cycle."""
        key = hash((inlier.tobytes(), nearest[inlier].tobytes()))
        cycle = key != self.last and key in self.seen
        self.seen.add(key)
        self.last = key
        return cycle


def _checked(src: np.ndarray, tgt: np.ndarray, R0: np.ndarray, t0: np.ndarray, max_distance: float,
             max_iterations: int):
    """The inputs as float64 arrays, or ``ValueError``."""
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    R = np.asarray(R0, dtype=np.float64)
    t = np.asarray(t0, dtype=np.float64)
    for name, array in (("src", src), ("tgt", tgt)):
        if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] == 0:
            raise ValueError(f"{name} must be (N, 3) with N >= 1, got {array.shape}")
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"R0 must be (3, 3) and t0 (3,), got {R.shape} and {t.shape}")
    if not max_distance > 0:
        raise ValueError(f"max_distance must be positive, got {max_distance}")
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be >= 0, got {max_iterations}")
    return src, tgt, R, t


def rms_radius(points: np.ndarray) -> float:
    """:func:`service.normalization.rms_radius` of ``points (M, 3)``, at least the smallest positive float (a
    divisor)."""
    return max(normalization.rms_radius(points), np.finfo(np.float64).tiny)


def _pairs(tree: KDTree, src_tree: KDTree | None, src_in_tgt: np.ndarray, tgt: np.ndarray, R: np.ndarray,
           t: np.ndarray, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Kept pairs ``inlier (N,)`` and nearest target index ``(N,)`` of the moved source ``src_in_tgt (N, 3)``.

    A pair is kept when it is closer than ``max_distance`` and, with ``src_tree`` (the unmoved
    source's tree), when the source point is also the target point's nearest source point.
    """
    dist, nearest = tree.query(src_in_tgt, k=1, distance_upper_bound=max_distance)  # [N], [N]
    inlier = dist < max_distance  # [N]; misses come back as inf
    if src_tree is not None:
        candidates = np.flatnonzero(inlier)
        partners = nearest[candidates]  # [C] target points some source point picked
        needed, where = np.unique(partners, return_inverse=True)  # only these need their nearest source
        nearest_src = src_tree.query((tgt[needed] - t) @ R, k=1)[1]  # R^T (tgt - t): target in the source frame
        inlier[candidates] = nearest_src[where] == candidates
    return inlier, nearest


def _result(tree: KDTree, src: np.ndarray, R: np.ndarray, t: np.ndarray, iterations: int, max_distance: float,
            warnings: tuple[str, ...] = ()) -> IcpResult:
    """:class:`IcpResult` of the pose ``(R, t)``: point-to-point statistics at ``max_distance``."""
    dist, _ = tree.query(src @ R.T + t, k=1, distance_upper_bound=max_distance)  # [N]
    inlier_dist = dist[dist < max_distance]
    residual_rms = float(np.sqrt(np.mean(inlier_dist**2))) if inlier_dist.size else 0.0
    return IcpResult(
        rotation=R,
        translation=t,
        iterations=iterations,
        inlier_ratio=float(inlier_dist.size / src.shape[0]),
        residual_rms=residual_rms,
        converged=not warnings,
        warnings=warnings,
    )
