"""Stage 3, normalise: the similarity normalisation of the working clouds, and poses back to the caller's units."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from service.feature_match import FeaturePose, feature_pose
from service.free_space import COARSE_VIEW_NEIGHBOURS, RangeView, range_view
from service.icp import NORMAL_NEIGHBOURS, LazySurface, Surface
from service.kdtree import KDTree
from service.neighbours import knn_graph
from service.normalization import Normalization
from service.per_instance_cache import per_instance_cached_property
from service.plane_frames import CloudFrame, cloud_frame, frame_rotations
from service.procrustes import compose
from service.quality import attainable_inlier_ratio, attainable_on_surface, degenerate, nearest_other_distances
from service.sampling import hashed_indices
from service.stages.sample import Sampled

INLIER_DISTANCE = 0.05  # normalised units (the paper's match threshold): quality inliers
ICP_DISTANCE = 0.1  # normalised units: default ICP correspondence distance
# The candidates' short refinements (service.stages.refine.short_refine) move every SHORT_REFINE_STRIDE-th point of
# the refinement's source: they only rank basins, and the winner's full refinement moves every point.
SHORT_REFINE_STRIDE = 3
# The fine clouds: up to FINE_SOURCE_POINTS of the entered source and FINE_TARGET_POINTS of the entered target, on
# which the free-space check and the descriptor consensus judge a pose (docs/decisions/0018-fine-refinement-on-denser-
# clouds.md). The fine stage (service.stages.fine) moves up to PRECISE_SOURCE_POINTS of the entered source onto every
# point of the entered target (docs/decisions/0122-the-fine-stage-on-the-whole-target.md).
FINE_SOURCE_POINTS = 2048
FINE_TARGET_POINTS = 2048
PRECISE_SOURCE_POINTS = 8192
# An entered cloud with at least this many times its working cloud's points samples its surface densely: the target's
# surface then stands in for its working samples (service.stages.ranking.close_fit), and either cloud's density can
# tell a range image (Working.range_views).
CLOSE_FIT_DENSITY = 4


def samples_densely(entered: np.ndarray, working: np.ndarray) -> bool:
    """Whether an ``entered`` cloud holds at least ``CLOSE_FIT_DENSITY`` times its ``working`` cloud's points."""
    return len(entered) >= CLOSE_FIT_DENSITY * len(working)


@dataclass(frozen=True, eq=False)
class Working(Sampled):
    """One registration's working clouds (:class:`service.stages.sample.Sampled`) and their normalisation, shared by
    the plain pass and the search of ``rotation_search="auto"``."""

    norm: Normalization
    src_n: np.ndarray  # [Ns, 3] float32, normalised (after the initial guess)
    tgt_n: np.ndarray  # [Nt, 3] float32, normalised

    @property
    def inlier_distance(self) -> float:
        """``INLIER_DISTANCE`` in the caller's units."""
        return INLIER_DISTANCE * self.norm.scale

    @per_instance_cached_property
    def searchable(self) -> bool:
        """Whether neither working cloud is degenerate (:func:`service.quality.degenerate`): ``auto`` searches, or
        starts its search ahead, only then."""
        return not (degenerate(self.src_w) or degenerate(self.tgt_w))

    @per_instance_cached_property
    def target_spacings(self) -> np.ndarray:
        """``[Nt]`` each working target point's distance to its nearest other one
        (:func:`service.quality.nearest_other_distances`; needs ``Nt >= 2``), measured once per registration."""
        return nearest_other_distances(self.tgt_w)

    @per_instance_cached_property
    def attainable_ratio(self) -> float:
        """The inlier ratio a right pose can reach at the working target's density
        (:func:`service.quality.attainable_inlier_ratio`), computed once per registration."""
        if len(self.tgt_w) < 2:
            return 1.0
        return attainable_inlier_ratio(self.tgt_w, self.inlier_distance, nearest_other=self.target_spacings)

    @per_instance_cached_property
    def surface_attainable_ratio(self) -> float:
        """The inlier ratio a right pose reaches on the target's surface: :func:`service.quality.attainable_on_surface`
        of :attr:`fine_target` against the working target, computed once per registration (the plain pass and the
        search both assess a pose)."""
        return attainable_on_surface(self.fine_target, self.tgt_w, self.inlier_distance)

    @per_instance_cached_property
    def source_attainable_ratio(self) -> float:
        """The inlier ratio a right pose reaches measured from the target's side (:func:`service.quality.reverse_fit`):
        :func:`service.quality.attainable_on_surface` of :attr:`fine_source` against the working source where the
        entered source samples its surface densely, else the working source's
        :func:`service.quality.attainable_inlier_ratio`; computed once per registration, where first asked."""
        if samples_densely(self.src_e, self.src_w):
            return attainable_on_surface(self.fine_source, self.working_source, self.inlier_distance)
        if len(self.working_source) < 2:
            return 1.0
        return attainable_inlier_ratio(self.working_source, self.inlier_distance)

    @per_instance_cached_property
    def feature_pose(self) -> FeaturePose | None:
        """The coarse pose of the entered source, moved by the initial guess, onto the entered target from matched
        local descriptors (:func:`service.feature_match.feature_pose`), on a grid of the larger of the two working
        clouds' median nearest-neighbour spacings (the working clouds are spread samples of a fixed size, so the
        coarser surface gets about that many cells and the other no more); computed once per registration, where first
        asked (the feature candidate, the consensus stage)."""
        voxel = float(max(np.median(nearest_other_distances(self.src_w)), np.median(self.target_spacings)))
        return feature_pose(self.src_e @ self.R_init.T + self.t_init, self.tgt_e, voxel)

    @per_instance_cached_property
    def range_views(self) -> tuple[RangeView | None, RangeView | None]:
        """The entered source's and target's :func:`service.free_space.range_view`, each ``None`` unless the cloud
        samples its surface densely (``CLOSE_FIT_DENSITY`` times its working cloud's points) as a range image does;
        built once per registration, when the free-space or the consensus stage first asks (from
        :attr:`entered_source_tree` and :attr:`entered_target_tree`)."""
        return (range_view(self.src_e, self.entered_source_tree) if samples_densely(self.src_e, self.src_w) else None,
                range_view(self.tgt_e, self.entered_target_tree) if samples_densely(self.tgt_e, self.tgt_w) else None)

    @per_instance_cached_property
    def confirming_views(self) -> tuple[RangeView | None, RangeView | None]:
        """The views a confirmation by free space reads: :attr:`range_views`, where a dense cloud has none, its view
        read over ``COARSE_VIEW_NEIGHBOURS`` (a range image with range noise of a point spacing), kept only where the
        other cloud has a view as well (a fused fragment cut by a plane can pass the coarser reading alone). Built only
        for a result free space may confirm: the coarser reading takes about twice the time (``docs/decisions/0094``).
        """
        fine_source, fine_target = self.range_views
        source_view, target_view = fine_source, fine_target
        if source_view is None and samples_densely(self.src_e, self.src_w):
            source_view = range_view(self.src_e, self.entered_source_tree, neighbours=COARSE_VIEW_NEIGHBOURS)
        if target_view is None and samples_densely(self.tgt_e, self.tgt_w):
            target_view = range_view(self.tgt_e, self.entered_target_tree, neighbours=COARSE_VIEW_NEIGHBOURS)
        if source_view is None or target_view is None:
            return fine_source, fine_target
        return source_view, target_view

    @per_instance_cached_property
    def source_frame(self) -> CloudFrame:
        """The normalised working source's normals and plane frame (:func:`service.plane_frames.cloud_frame`), found
        once per registration: the frame rotations and the symmetry check's off-plane points both ask."""
        return cloud_frame(self.src_n)

    @per_instance_cached_property
    def plane_frame_rotations(self) -> np.ndarray | None:
        """``[24, 3, 3]``: the rotations between the normalised working clouds' plane frames
        (:func:`service.plane_frames.frame_rotations`), or ``None`` unless both are built of orthogonal planes;
        found once per registration (``auto`` and the search both ask)."""
        return frame_rotations(self.src_n, self.tgt_n, self.source_frame)

    @per_instance_cached_property
    def entered_source_tree(self) -> KDTree:
        """KD-tree of the entered source ``src_e``, built when its range views are first read."""
        return KDTree(np.asarray(self.src_e, dtype=np.float64))

    @per_instance_cached_property
    def entered_target64(self) -> np.ndarray:
        """``[Me, 3]`` float64: the entered target ``tgt_e``, converted once for its tree and its surface."""
        return np.ascontiguousarray(self.tgt_e, dtype=np.float64)

    @per_instance_cached_property
    def entered_target_tree(self) -> KDTree:
        """KD-tree of the entered target ``tgt_e`` (all of the caller's target up to the entry limit), built when a
        stage first measures distances to the target's surface rather than to its working samples."""
        return KDTree(self.entered_target64)

    @per_instance_cached_property
    def working_graphs(self) -> tuple[np.ndarray, np.ndarray]:
        """``[Ns, K]``, ``[Nt, K]`` (``K = NORMAL_NEIGHBOURS``): each normalised working cloud's nearest rows, nearest
        first, itself included; one query per cloud for the network's neighbour graph and, where the refinement
        moves the working clouds themselves, for its normals."""
        return knn_graph(self.src_n[None], NORMAL_NEIGHBOURS)[0], knn_graph(self.tgt_n[None], NORMAL_NEIGHBOURS)[0]

    @per_instance_cached_property
    def target_surface(self) -> Surface:
        """KD-tree and normals of the refinement's target ``tgt_r``, built once per registration."""
        nearest = self.working_graphs[1] if self.tgt_r is self.tgt_w else None
        return Surface.of(self.tgt_r, nearest_rows=nearest)

    def working_target_lookup(self, surface: Surface | None) -> tuple[KDTree, Surface | None]:
        """A KD-tree of the working target ``tgt_w`` and its normals where they are at hand: ``surface`` (the
        refinement's, of ``tgt_r``) when the refinement aligns with the working target itself, else a new tree and
        ``None`` (:func:`service.stability.pose_stability` then computes the normals it needs)."""
        working = surface if surface is not None and self.tgt_r is self.tgt_w else None
        return (KDTree(self.tgt_w) if working is None else working.tree), working

    @per_instance_cached_property
    def source_surface(self) -> Surface:
        """KD-tree and normals of the refinement's source ``src_r`` in its own frame, built once per registration:
        every start of every refinement moves the same points."""
        nearest = self.working_graphs[0] if self.src_r is self.working_source else None  # src_w: the same rows, moved
        return Surface.of(np.asarray(self.src_r, dtype=np.float64), nearest_rows=nearest)

    @per_instance_cached_property
    def fine_source(self) -> np.ndarray:
        """``[Nf, 3]`` float64: up to ``FINE_SOURCE_POINTS`` points of the entered source ``src_e``, a uniform
        subsample (:func:`service.sampling.hashed_indices`), caller's frame: what the descriptor consensus moves and
        the free-space check projects. The first rows of :attr:`precise_source` (in hash order: the lowest hashes),
        so the entered source is hashed once."""
        return self.precise_source[:FINE_SOURCE_POINTS]

    @per_instance_cached_property
    def fine_target(self) -> np.ndarray:
        """``[Mf, 3]`` float64: up to ``FINE_TARGET_POINTS`` points of the entered target ``tgt_e``, a uniform
        subsample as :attr:`fine_source`."""
        return np.asarray(self.tgt_e[hashed_indices(self.tgt_e, FINE_TARGET_POINTS)], dtype=np.float64)

    @per_instance_cached_property
    def fine_target_surface(self) -> Surface:
        """KD-tree and normals of :attr:`fine_target`, built once per registration."""
        return Surface.of(self.fine_target)

    @per_instance_cached_property
    def precise_source(self) -> np.ndarray:
        """``[Np, 3]`` float64: up to ``PRECISE_SOURCE_POINTS`` points of the entered source, a uniform subsample
        (:func:`service.sampling.hashed_indices`, in hash order), caller's frame: what the fine stage moves."""
        return np.asarray(self.src_e[hashed_indices(self.src_e, PRECISE_SOURCE_POINTS)], dtype=np.float64)

    @per_instance_cached_property
    def entered_target_surface(self) -> LazySurface:
        """The entered target's KD-tree (:attr:`entered_target_tree`), with the normals of the points a refinement
        pairs, computed as it pairs them: what the fine stage moves :attr:`precise_source` onto. A target that
        repeats its points gives a normal its neighbours from its distinct points (:mod:`service.distinct_neighbours`).
        """
        return LazySurface(self.entered_target64, self.entered_target_tree)

    @per_instance_cached_property
    def short_points(self) -> np.ndarray:
        """Every ``SHORT_REFINE_STRIDE``-th row of ``src_r`` ``[Nr', 3]`` (float64; a spread subsample: the working
        cloud is in farthest-point order): what the candidates' short refinements move."""
        return np.asarray(self.src_r, dtype=np.float64)[::SHORT_REFINE_STRIDE]

    @per_instance_cached_property
    def short_surface(self) -> Surface:
        """The surface of :attr:`short_points`: its own KD-tree, the full source's normals."""
        full = self.source_surface
        rows = slice(None, None, SHORT_REFINE_STRIDE)
        return Surface(KDTree(self.short_points), full.normals[rows], full.defined[rows])


def normalise(sampled: Sampled, reference_radius: float) -> Working:
    """Fit :class:`service.normalization.Normalization` to the working clouds and apply it (float32)."""
    norm = Normalization.fit(sampled.src_w, sampled.tgt_w, reference_radius)
    src_n, tgt_n = norm.apply_src(sampled.src_w).astype(np.float32), norm.apply_tgt(sampled.tgt_w).astype(np.float32)
    return Working(**{f.name: getattr(sampled, f.name) for f in fields(Sampled)}, norm=norm, src_n=src_n, tgt_n=tgt_n)


def to_caller(work: Working, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose between normalised clouds -> caller's ``src_to_tgt``, composed after the initial guess."""
    R_c, t_c = work.norm.unnormalize_pose(R, t)
    return compose(R_c, t_c, work.R_init, work.t_init)
