"""The network's iteration loop on a batch of normalised working clouds, resumable and prunable.

``Registrar.run_network`` = :meth:`Registrar.start_network` (encoder, keypoints) + :meth:`NetworkLoop.advance`
to the last iteration + :meth:`NetworkLoop.outputs`. The rotation search advances every start rotation by
a first iteration, keeps the most promising few (:meth:`NetworkLoop.select`) and advances only those to the
end: each row of the batch runs the same arithmetic whichever rows share its batch, so a pruned hypothesis
ends exactly where the unpruned loop would have taken it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from service.procrustes import compose, weighted_procrustes


@dataclass
class NetworkOutput:
    """What the network loop returns for one pair of normalised working clouds."""

    rotation: np.ndarray  # [3, 3] src_to_tgt (normalised frame)
    translation: np.ndarray  # [3]
    src_kp: np.ndarray  # [K] keypoint indices into the working source
    tgt_kp: np.ndarray  # [L] into the working target
    matched: np.ndarray  # [K] index into tgt_kp (last iteration)
    credibility: np.ndarray  # [K] in [0, 1] (last iteration)
    weights: np.ndarray  # [K] median-thresholded credibilities (last iteration)
    cumulative: list[tuple[np.ndarray, np.ndarray]]  # pose after each iteration
    min_top2_gap: float  # smallest gap between a keypoint's two best scores (argmax ties)
    min_median_gap: float  # smallest gap between the median credibility and the next lower one


class DeferredOutput:
    """A :class:`NetworkOutput` computed when first read, once (thread-safe): a candidate's network pass whose
    correspondences are reported only should it win (``docs/decisions/0056-network-passes-only-for-the-winner.md``)."""

    def __init__(self, compute: Callable[[], NetworkOutput]) -> None:
        self._compute: Callable[[], NetworkOutput] | None = compute
        self._output: NetworkOutput | None = None
        self._lock = threading.Lock()

    @property
    def computed(self) -> bool:
        """Whether the output was read (and so computed) already."""
        return self._output is not None

    def get(self) -> NetworkOutput:
        """The output, computed on the first call."""
        with self._lock:
            if self._output is None:
                assert self._compute is not None
                self._output, self._compute = self._compute(), None  # drop the clouds the computation held
            return self._output


def sigmoid(logit: np.ndarray) -> np.ndarray:
    """``1 / (1 + exp(-logit))`` in float64; logits beyond +-700 (degenerate clouds) saturate to 0 or 1 instead of
    overflowing ``exp``."""
    return 1.0 / (1.0 + np.exp(-np.clip(logit.astype(np.float64), -700.0, 700.0)))


def lower_median_weights(credibility: np.ndarray) -> np.ndarray:
    """Credibilities at or above the lower median of their row, others zeroed (``[..., K] -> [..., K]``)."""
    k = (credibility.shape[-1] - 1) // 2
    median = np.partition(credibility, k, axis=-1)[..., k : k + 1]  # [..., 1]
    return credibility * (credibility >= median)


def gather_rows(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``values [B, N, C]`` at ``idx [B, K]`` -> ``[B, K, C]``."""
    return np.take_along_axis(values, idx[..., None], axis=1)


# Registrar.match: (iteration, src_xyz [B, K, 3], tgt_xyz [B, L, 3], src_emb, tgt_emb, emb_dist) -> scores, logits
Matcher = Callable[..., tuple[np.ndarray, np.ndarray]]


@dataclass
class NetworkLoop:
    """The loop's state for ``B`` pairs after ``done`` iterations (every array's first axis is ``B``)."""

    match: Matcher
    centroid: str  # weighted_procrustes' centroid rule of the model
    src_kp: np.ndarray  # [B, K] keypoints of each source
    tgt_kp: np.ndarray  # [B, L] keypoints of each target
    ps: np.ndarray  # [B, K, 3] float64 source keypoints, moved by the pose so far
    pt: np.ndarray  # [B, L, 3] target keypoints
    fs: np.ndarray  # [B, K, D] source keypoint embeddings
    ft: np.ndarray  # [B, L, D]
    emb_dist: np.ndarray | None  # [B, K, L] embedding distances (matcher input), or None for older graphs
    rotation: np.ndarray  # [B, 3, 3] pose so far
    translation: np.ndarray  # [B, 3]
    cumulative: list[tuple[np.ndarray, np.ndarray]]  # ([B, 3, 3], [B, 3]) after each iteration done
    min_gap: np.ndarray  # [B]
    median_gap: np.ndarray  # [B]
    matched: np.ndarray | None = None  # [B, K] (last iteration)
    credibility: np.ndarray | None = None  # [B, K]
    weights: np.ndarray | None = None  # [B, K]
    done: int = 0

    def advance(self, until: int, timing: dict[str, float], batch: int | None = None) -> None:
        """Run iterations ``done .. until - 1``, the matcher on at most ``batch`` rows per call (all by default).

        Adds the matcher time to ``timing["iterations"]`` and the rest (argmax, weights, SVD) to ``timing["svd"]``.
        """
        B, L = self.ps.shape[0], self.pt.shape[1]
        step = batch or B
        for it in range(self.done, until):
            tic = time.perf_counter()
            parts = [
                self.match(it, self.ps[r : r + step], self.pt[r : r + step], self.fs[r : r + step],
                           self.ft[r : r + step], None if self.emb_dist is None else self.emb_dist[r : r + step])
                for r in range(0, B, step)
            ]
            scores = np.concatenate([p[0] for p in parts])  # [B, K, L]
            logit = np.concatenate([p[1] for p in parts])  # [B, K]
            toc = time.perf_counter()
            matched = scores.argmax(axis=2)  # [B, K]
            if L > 1:
                top2 = np.partition(scores, -2, axis=2)[..., -2:]  # [B, K, 2]
                self.min_gap = np.minimum(self.min_gap, (top2[..., 1] - top2[..., 0]).min(axis=1))
            credibility = sigmoid(logit)  # [B, K]
            weights = lower_median_weights(credibility)  # [B, K]
            kept = weights > 0
            has_below = (~kept).any(axis=1)  # [B]
            gap = np.where(kept, credibility, np.inf).min(1) - np.where(kept, -np.inf, credibility).max(1)
            self.median_gap = np.where(has_below, np.minimum(self.median_gap, gap), self.median_gap)
            partners = gather_rows(self.pt, matched).astype(np.float64)  # [B, K, 3]
            R, t = weighted_procrustes(self.ps, partners, weights, self.centroid)
            self.ps = self.ps @ R.transpose(0, 2, 1) + t[:, None]  # [B, K, 3]
            self.rotation, self.translation = compose(R, t, self.rotation, self.translation)
            self.cumulative.append((self.rotation, self.translation))
            self.matched, self.credibility, self.weights, self.done = matched, credibility, weights, it + 1
            timing["iterations"] = timing.get("iterations", 0.0) + 1000 * (toc - tic)
            timing["svd"] = timing.get("svd", 0.0) + 1000 * (time.perf_counter() - toc)

    def select(self, rows: np.ndarray) -> NetworkLoop:
        """The loop of the given batch ``rows`` only (same state, fewer pairs)."""
        def take(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else values[rows]

        return replace(
            self, src_kp=take(self.src_kp), tgt_kp=take(self.tgt_kp), ps=take(self.ps), pt=take(self.pt),
            fs=take(self.fs), ft=take(self.ft), emb_dist=take(self.emb_dist), rotation=take(self.rotation),
            translation=take(self.translation), cumulative=[(R[rows], t[rows]) for R, t in self.cumulative],
            min_gap=take(self.min_gap), median_gap=take(self.median_gap), matched=take(self.matched),
            credibility=take(self.credibility), weights=take(self.weights),
        )

    @staticmethod
    def join(loops: list[NetworkLoop]) -> NetworkLoop:
        """One loop of the batches of ``loops`` (the same model and iterations done), in order."""
        first = loops[0]
        if any(loop.done != first.done for loop in loops):
            raise ValueError("NetworkLoop.join: the loops are at different iterations")
        def cat(name: str) -> np.ndarray | None:
            if getattr(first, name) is None:
                return None
            return np.concatenate([getattr(loop, name) for loop in loops])

        return replace(
            first, **{name: cat(name) for name in (
                "src_kp", "tgt_kp", "ps", "pt", "fs", "ft", "emb_dist", "rotation", "translation", "min_gap",
                "median_gap", "matched", "credibility", "weights")},
            cumulative=[
                (np.concatenate([loop.cumulative[i][0] for loop in loops]),
                 np.concatenate([loop.cumulative[i][1] for loop in loops]))
                for i in range(first.done)
            ],
        )

    def outputs(self) -> list[NetworkOutput]:
        """One :class:`NetworkOutput` per pair (after at least one iteration)."""
        if self.done == 0:
            raise ValueError("NetworkLoop.outputs: no iteration has run")
        return [
            NetworkOutput(
                self.rotation[b], self.translation[b], self.src_kp[b], self.tgt_kp[b], self.matched[b],
                self.credibility[b], self.weights[b], [(R[b], t[b]) for R, t in self.cumulative],
                float(self.min_gap[b]), float(self.median_gap[b]),
            )
            for b in range(self.ps.shape[0])
        ]
