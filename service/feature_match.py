"""A coarse ``src_to_tgt`` pose at any orientation from matched local descriptors (:mod:`service.features`).

Both clouds are reduced to the means of a common voxel grid and described; descriptors that are each other's nearest
neighbour pair the points; triplets of pairs whose side lengths agree give candidate poses (RANSAC), and the pose that
brings the most pairs within ``INLIER_VOXELS`` voxels of each other wins, refitted on those pairs. Its ``support``
(that count) says how much of the surface agrees: a few pairs agree by chance, dozens do not. Its ``rival()`` says
whether they point to one place: the support of the best pose that agrees with other pairs
(``docs/decisions/0091-a-replaced-round-objects-turn-needs-one-place.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.features import DESCRIBED_NEIGHBOURS, describe, voxel_means
from service.procrustes import weighted_procrustes

RADIUS_VOXELS = 5.0  # descriptor radius, in voxels
INLIER_VOXELS = 2.0  # a pair agrees with a pose within this distance, in voxels
TRIPLETS = 20_000  # RANSAC samples (seeded: the same clouds give the same pose; decisions/0047)
SIDE_AGREEMENT = 0.9  # a triplet's sides in the two clouds within this ratio of each other
MIN_SIDE_VOXELS = 2.0  # ... and none shorter than this (nearly coincident points fix no rotation)
# At most this many cells per reduced cloud (the grid coarsened until both fit): the descriptor distances take
# 4 * MAX_CELLS**2 bytes. The real-scan set's clouds reduce to at most 1,700 cells on the working spacing.
MAX_CELLS = 4000
SCORED_AT_ONCE = 500  # RANSAC poses scored per batch ([SCORED_AT_ONCE, C, 3] float32)
# A RANSAC pose that shares at most this share of its agreeing pairs with the best's is another pose (FeaturePose.rival)
DISTINCT_SHARED = 0.5


@dataclass(frozen=True)
class Hypotheses:
    """The RANSAC poses a feature pose was chosen from."""

    rotation: np.ndarray  # [H, 3, 3] src_to_tgt
    translation: np.ndarray  # [H, 3]
    support: np.ndarray  # [H] matched pairs within the agreement distance at each


@dataclass(frozen=True)
class FeaturePose:
    """A coarse pose and how many matched pairs agree with it."""

    rotation: np.ndarray  # [3, 3] src_to_tgt
    translation: np.ndarray  # [3]
    support: int  # matched pairs within INLIER_VOXELS voxels at this pose
    matches: int  # mutual descriptor matches
    source_matched: np.ndarray  # [C, 3] the matched cells of the source ...
    target_matched: np.ndarray  # [C, 3] ... and of the target, pair by pair
    agreement: float  # INLIER_VOXELS voxels: the distance within which a pair agrees with a pose
    hypotheses: Hypotheses  # the RANSAC poses it was chosen from (the first with the most support), for rival()

    def support_of(self, R: np.ndarray, t: np.ndarray) -> int:
        """How many of the matched pairs agree with another ``src_to_tgt`` pose ``R [3, 3], t [3]``."""
        return int(agreeing(R[None], t[None], self.source_matched, self.target_matched, self.agreement)[0].sum())

    def rival(self, at_least: float = 0.0) -> int:
        """The most matched pairs another place the descriptors point to brings into agreement: the best support of
        the RANSAC poses that share at most ``DISTINCT_SHARED`` of their agreeing pairs with the chosen one's (0 where
        none does). Near ``support`` on a shape the descriptors cannot tell from itself turned or slid. Only poses with
        at least ``at_least`` pairs are scored (a caller that compares the rival with a threshold passes it): below
        it the rival counts as 0."""
        found = self.hypotheses
        best = int(found.support.argmax())
        chosen = agreeing(found.rotation[best:best + 1], found.translation[best:best + 1], self.source_matched,
                          self.target_matched, self.agreement)[0]  # [C]
        source, target = self.source_matched[~chosen], self.target_matched[~chosen]  # [C', 3] the pairs it leaves
        if len(source) == 0:  # the chosen pose brings every pair into agreement: only a pose with none is distinct
            return 0
        order = np.argsort(-found.support, kind="stable")  # [H] most support first: the first distinct one is the rival
        order = order[found.support[order] >= at_least]
        for start in range(0, len(order), SCORED_AT_ONCE):
            rows = order[start:start + SCORED_AT_ONCE]
            # distinct: at least 1 - DISTINCT_SHARED of its agreeing pairs are ones the chosen pose leaves
            elsewhere = agreeing(found.rotation[rows], found.translation[rows], source, target,
                                 self.agreement)  # [B, C']
            distinct = elsewhere.sum(axis=1) >= (1.0 - DISTINCT_SHARED) * found.support[rows]  # [B]
            if distinct.any():
                return int(found.support[rows][distinct][0])
        return 0

    def has_rival(self, share: float) -> bool:
        """Whether another place the descriptors point to (:meth:`rival`) has at least ``share`` of ``support``."""
        floor = share * self.support
        return self.rival(floor) >= floor


def mutual_matches(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``(i [C], j [C])`` of descriptors ``source [Ns, D]`` and ``target [Nt, D]`` that are each other's nearest
    neighbour (squared Euclidean distance)."""
    distance = (target * target).sum(axis=1)[None] - 2.0 * source @ target.T  # [Ns, Nt] up to a per-row constant
    nearest_target = distance.argmin(axis=1)  # [Ns]
    distance += (source * source).sum(axis=1)[:, None]
    nearest_source = distance.argmin(axis=0)  # [Nt]
    mutual = np.flatnonzero(nearest_source[nearest_target] == np.arange(len(source)))
    return mutual, nearest_target[mutual]


def feature_pose(source: np.ndarray, target: np.ndarray, voxel: float, seed: int = 0) -> FeaturePose | None:
    """The coarse pose of ``source [N, 3]`` onto ``target [M, 3]`` on a grid of ``voxel`` edges, or ``None`` where
    the grid has no positive size, a reduced cloud is too small to describe or no triplet of matches agrees in
    shape."""
    if not (np.isfinite(voxel) and voxel > 0):
        return None
    src, tgt = voxel_means(source, voxel), voxel_means(target, voxel)  # [Vs, 3], [Vt, 3]
    while max(len(src), len(tgt)) > MAX_CELLS:  # bounded memory: a coarser grid
        voxel *= 1.1 * np.sqrt(max(len(src), len(tgt)) / MAX_CELLS)
        src, tgt = voxel_means(source, voxel), voxel_means(target, voxel)
    if min(len(src), len(tgt)) <= DESCRIBED_NEIGHBOURS:
        return None
    radius = RADIUS_VOXELS * voxel
    i, j = mutual_matches(describe(src, radius), describe(tgt, radius))
    p, q = src[i], tgt[j]  # [C, 3] matched points
    if len(p) < 3:
        return None
    triplets = np.random.default_rng(seed).integers(0, len(p), size=(TRIPLETS, 3))  # [H, 3]
    p3, q3 = p[triplets], q[triplets]  # [H, 3, 3]
    sides_p = np.linalg.norm(p3 - p3[:, [1, 2, 0]], axis=2)  # [H, 3]
    sides_q = np.linalg.norm(q3 - q3[:, [1, 2, 0]], axis=2)
    agree = ((np.minimum(sides_p, sides_q) > SIDE_AGREEMENT * np.maximum(sides_p, sides_q)).all(axis=1)
             & (sides_p.min(axis=1) > MIN_SIDE_VOXELS * voxel))  # [H]
    if not agree.any():
        return None
    R, t = weighted_procrustes(p3[agree], q3[agree])  # [H', 3, 3], [H', 3]
    support = np.concatenate([agreeing(R[k:k + SCORED_AT_ONCE], t[k:k + SCORED_AT_ONCE], p, q, INLIER_VOXELS * voxel)
                              .sum(axis=1) for k in range(0, len(R), SCORED_AT_ONCE)])  # [H']
    best = int(support.argmax())  # the first of equals: seeded, so repeatable
    kept = agreeing(R[best:best + 1], t[best:best + 1], p, q, INLIER_VOXELS * voxel)[0]  # [C]
    R1, t1 = weighted_procrustes(p[kept], q[kept])
    return FeaturePose(R1, t1, int(support[best]), len(p), p, q, INLIER_VOXELS * voxel, Hypotheses(R, t, support))


def agreeing(R: np.ndarray, t: np.ndarray, p: np.ndarray, q: np.ndarray, distance: float) -> np.ndarray:
    """``[H, C]`` bool: which matched pairs ``p [C, 3] -> q [C, 3]`` lie within ``distance`` of each other at each of
    the poses ``R [H, 3, 3]``, ``t [H, 3]`` (float32)."""
    moved = np.einsum("hij,cj->hci", R.astype(np.float32), p.astype(np.float32)) + t[:, None].astype(np.float32)
    return ((moved - q.astype(np.float32)[None]) ** 2).sum(axis=2) < distance**2
