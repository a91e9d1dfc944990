"""The registration pipeline: ONNX Runtime for the networks, numpy for everything else.

``Registrar.register`` = validate -> resample to the working size -> similarity normalisation ->
encoder -> top-K keypoints -> n x (matcher -> argmax -> credibility weights -> weighted SVD ->
compose) -> back to the caller's units -> optional ICP (point-to-point or point-to-plane) -> quality record.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np
import onnxruntime as ort

from service.blas_threads import use_one_blas_thread
from service.errors import InputError
from service.icp import IcpResult, Surface, icp, icp_plane, refine_plane
from service.kdtree import KDTree
from service.manifest import Manifest, load_manifest
from service.multistart import best_turned_pose
from service.neighbours import knn_graph
from service.network_loop import NetworkLoop, NetworkOutput, gather_rows
from service.normalization import Normalization
from service.procrustes import compose, to_matrix
from service.quality import assess, attainable_inlier_ratio, degenerate
from service.refine_modes import REFINE_MODES, REFINE_POINTS_RANGE
from service.rotation_search import (
    SearchCandidate,
    ambiguity_warning,
    distinct_candidates,
    rank_hypotheses,
    search_hypotheses,
    search_rotations_for,
)
from service.sampling import evenly_spaced_indices, resample_indices, spread_indices
from service.stability import pose_stability, weak_motion_warning

MIN_POINTS = 32
MAX_ITERATIONS = 8
KEYPOINT_RANGE = (16, 512)
DEFAULT_WORKING_SIZE = 768
INLIER_DISTANCE = 0.05  # normalised units (the paper's match threshold): quality inliers
ICP_DISTANCE = 0.1  # normalised units: default ICP correspondence distance
SearchMode = bool | Literal["auto"]  # Registrar.register(rotation_search=...): False, True or "auto"
# rotation_search="auto" searches when the plain result's inlier ratio is below this share of the ratio a
# right pose can reach at the target's density (service.quality.attainable_inlier_ratio). Chosen on the
# bundled `general` model with refine="icp-plane" (docs/ROTATION_SEARCH.md, "The trigger"):
# right poses reach 0.93-0.98 of it on dense and sparse pairs alike; at 0.8 "auto" matched the former fixed
# threshold (inlier ratio 0.7) on dense pairs at 45/90/180 deg and on sparse pairs searched 5% instead of 77%
# of 300 pairs within 45 deg (recall at 5 deg 0.860 vs 0.870), with equal or better recall at 90 and 180 deg.
# Only the relative rule decides (since 2026-11-26, 07:25 UTC): the former extra "or not reliable" searched
# 3 more of those 300 pairs (targets too sparse to reach the reliable ratio at all) and made one worse.
AUTO_SEARCH_RELATIVE_RATIO = 0.8
# With a refinement, the rotation search's distinct kept candidates (service.rotation_search.SEARCH_KEEP) each get a
# short refinement -- the refinement's stages with at most CANDIDATE_ITERATIONS updates each -- and are ranked again
# by their fit on the working clouds; the winner then gets the full refinement. The search's own ranking (short
# point-to-point ICPs on its subsample) often put a wrong basin first: on 600 seeded pairs at 90 and 180 degrees
# 359 -> 388 right for ~15 ms more (docs/ROTATION_SEARCH.md, "Ranking the kept candidates again").
CANDIDATE_ITERATIONS = 3


def search_mode(rotation_search) -> Literal["off", "on", "auto"]:
    """``Registrar.register``'s ``rotation_search`` (``False``, ``True`` or ``"auto"``; ``None``: the default,
    ``False``) as a mode, or ``InputError``."""
    if rotation_search is None:
        return "off"
    if rotation_search is False or rotation_search is True or isinstance(rotation_search, np.bool_):
        return "on" if rotation_search else "off"
    if isinstance(rotation_search, str) and rotation_search == "auto":
        return "auto"
    raise InputError(f"rotation_search must be true, false or 'auto', got {rotation_search!r}")


def needs_search(result: RegistrationResult, attainable_ratio: float = 1.0) -> bool:
    """Whether ``rotation_search="auto"`` searches after the plain ``result``: its inlier ratio is below
    ``AUTO_SEARCH_RELATIVE_RATIO`` times ``attainable_ratio`` (:func:`service.quality.attainable_inlier_ratio`
    of the working target). The registrar never searches degenerate clouds (:func:`service.quality.degenerate`)."""
    return result.inlier_ratio < AUTO_SEARCH_RELATIVE_RATIO * attainable_ratio


def default_threads() -> int:
    return max(1, min(2, os.cpu_count() or 1))


def check_cloud(points, name: str) -> np.ndarray:
    """``points`` as float64 ``[N, 3]`` with ``N >= MIN_POINTS`` and finite values, or ``InputError``."""
    arr = np.asarray(points)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name}: expected numbers, got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected shape [N, 3], got {list(arr.shape)}")
    if arr.shape[0] < MIN_POINTS:
        raise InputError(f"{name}: needs at least {MIN_POINTS} points, got {arr.shape[0]}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise InputError(f"{name}: contains NaN or infinite coordinates")
    if np.abs(arr).max() > np.finfo(np.float32).max:
        raise InputError(f"{name}: coordinates overflow float32")
    return arr


def top_k(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` highest ``scores [N]``, highest first (ties: lower index first)."""
    idx = np.argpartition(-scores, k - 1)[:k] if k < len(scores) else np.arange(len(scores))
    return idx[np.lexsort((idx, -scores[idx]))]


def embedding_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``||a_i - b_j||`` ``[B, K, L]`` (float32) of embeddings ``a [B, K, D]``, ``b [B, L, D]``.

    Computed as ``|a|^2 + |b|^2 - 2 a.b`` in float64: the cancellation error (~1e-16 |a|^2) is far
    below float32 rounding, so the result agrees with an explicit-difference float32 distance.
    """
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    d2 = (a64 * a64).sum(-1)[:, :, None] + (b64 * b64).sum(-1)[:, None, :] - 2.0 * (a64 @ b64.transpose(0, 2, 1))
    return np.sqrt(np.maximum(d2, 0.0)).astype(np.float32)


@dataclass
class IterationPose:
    rotation: np.ndarray  # [3, 3] cumulative src_to_tgt after this iteration (caller's units)
    translation: np.ndarray  # [3]


@dataclass
class RegistrationResult:
    rotation: np.ndarray  # [3, 3] src_to_tgt
    translation: np.ndarray  # [3]
    source_index: np.ndarray  # [K] int64 into the caller's source array
    target_index: np.ndarray  # [K] int64 into the caller's target array
    credibility: np.ndarray  # [K] sigmoid of the credibility logit, in [0, 1]
    weight: np.ndarray  # [K] SVD weight after the median threshold (sums to ~1)
    inlier_ratio: float
    residual_rms: float
    reliable: bool
    warnings: list[str]
    iterations: int
    timing_ms: dict[str, float]
    iteration_poses: list[IterationPose] = field(default_factory=list)
    stability: float | None = None  # service.stability: below WEAK_EIGENVALUE the pose is weakly constrained

    @property
    def transform(self) -> np.ndarray:
        """``[4, 4]`` homogeneous src_to_tgt."""
        return to_matrix(self.rotation, self.translation)


@dataclass(frozen=True)
class EmbeddedCloud:
    """A working cloud's encoder output, reused across network runs (the rotation search's target)."""

    embedding: np.ndarray  # [1, M, D]
    scores: np.ndarray  # [1, M] keypoint significance


@dataclass
class _Working:
    """One registration's working clouds, shared by the plain pass and the search of ``rotation_search="auto"``."""

    src: np.ndarray  # [N, 3] the caller's source (float64)
    idx_s: np.ndarray  # [Ns] working source rows
    idx_t: np.ndarray  # [Nt] working target rows
    tgt_w: np.ndarray  # [Nt, 3] working target, caller's units
    src_r: np.ndarray  # [Nr, 3] the source points the refinement moves, caller's units
    tgt_r: np.ndarray  # [Mr, 3] the target points it aligns them with
    norm: Normalization
    src_n: np.ndarray  # [Ns, 3] float32, normalised (after the initial guess)
    tgt_n: np.ndarray  # [Nt, 3] float32, normalised
    R_init: np.ndarray  # [3, 3] initial guess
    t_init: np.ndarray  # [3]


def session_options(threads: int) -> ort.SessionOptions:
    """The ONNX Runtime options of every graph session of a :class:`Registrar` (``threads`` intra-op threads)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # One thread pool per session: idle pools must not spin, or the encoder's and each matcher's
    # threads fight for the same cores between consecutive calls (measured: 4x slower loop).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    # No memory pattern: after the first run ORT planned one extra block per session for the
    # shapes it saw, on top of its arena (+80 MB RSS from the second call on, same latency;
    # docs/BENCHMARKS.md, "HTTP overhead").
    options.enable_mem_pattern = False
    return options


class Registrar:
    """One loaded, hash-verified model: an ONNX Runtime session per graph, shared by all callers.

    Built on the main thread, it also sets numpy's BLAS to one thread for the process
    (:func:`service.blas_threads.use_one_blas_thread`): ONNX Runtime's threads own the cores.
    """

    def __init__(self, model_dir: str | Path, threads: int | None = None, warmup: bool = True):
        use_one_blas_thread()
        self.manifest: Manifest = load_manifest(model_dir)
        self.name = self.manifest.name
        self.config = self.manifest.config
        self.reference_radius = float(self.manifest.normalization.get("reference_radius", 1.0))
        self.centroid = self.config.get("centroid", "weighted")
        options = session_options(threads or default_threads())
        providers = ["CPUExecutionProvider"]
        started = time.perf_counter()
        self.encoder = ort.InferenceSession(self.manifest.graph_bytes("encoder"), options, providers=providers)
        self.matchers = [
            ort.InferenceSession(self.manifest.graph_bytes(role), options, providers=providers)
            for role in self.manifest.matcher_roles
        ]
        self.encoder_takes_neighbours = any(i.name == "neighbours" for i in self.encoder.get_inputs())
        self.matcher_takes_distance = any(i.name == "emb_dist" for i in self.matchers[0].get_inputs())
        self.knn = int(self.config.get("knn", 12))
        self.default_iterations = int(self.config.get("iterations", len(self.matchers)))
        self.default_keypoints = int(self.config.get("keypoints", 128))
        self.ready = threading.Event()
        if warmup:
            self.warm_up()
        self.load_seconds = time.perf_counter() - started

    def warm_up(self) -> None:
        """Run a synthetic pair once so the first request does not pay for allocations."""
        rng = np.random.default_rng(0)
        cloud = rng.normal(size=(DEFAULT_WORKING_SIZE, 3))
        self.register(cloud, cloud + 0.01)
        self.ready.set()

    # -- network calls ---------------------------------------------------------------------------
    def neighbours(self, points: np.ndarray) -> np.ndarray:
        """The encoder's k-NN graph ``[B, N, k]`` of ``points [B, N, 3]``."""
        return knn_graph(points, self.knn)

    def embed(self, points: np.ndarray, neighbours: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``[B, N, 3]`` float32 -> embeddings ``[B, N, D]``, scores ``[B, N]``.

        ``neighbours [B, N, k]``: the k-NN graph when the caller has it (else built here). Graphs
        exported before the graph became an input compute it themselves and ignore it.
        """
        feeds = {"points": points.astype(np.float32, copy=False)}
        if self.encoder_takes_neighbours:
            feeds["neighbours"] = self.neighbours(feeds["points"]) if neighbours is None else neighbours
        emb, score = self.encoder.run(None, feeds)
        return emb, score

    def embed_cloud(self, points: np.ndarray) -> EmbeddedCloud:
        """The encoder output of one working cloud ``[M, 3]`` (float32), for :meth:`run_network`'s ``target``."""
        cloud = points[None]  # [1, M, 3]
        neighbours = self.neighbours(cloud) if self.encoder_takes_neighbours else None
        return EmbeddedCloud(*self.embed(cloud, neighbours))

    def match(self, iteration: int, src_xyz, tgt_xyz, src_emb, tgt_emb,
              emb_dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Matching scores ``[B, K, L]`` and credibility logits ``[B, K]`` of one iteration.

        ``emb_dist [B, K, L]``: :func:`embedding_distance` of the embeddings when the caller has it
        (it is the same in every iteration); graphs exported before it became an input ignore it.
        """
        session = self.matchers[min(iteration, len(self.matchers) - 1)]
        feeds = {
            "src_xyz": src_xyz.astype(np.float32, copy=False),
            "tgt_xyz": tgt_xyz.astype(np.float32, copy=False),
            "src_emb": src_emb,
            "tgt_emb": tgt_emb,
        }
        if self.matcher_takes_distance:
            feeds["emb_dist"] = embedding_distance(src_emb, tgt_emb) if emb_dist is None else emb_dist
        scores, logit = session.run(None, feeds)
        return scores, logit

    def start_network(
        self,
        src_n: np.ndarray,
        tgt_n: np.ndarray,
        keypoints: int,
        timing: dict[str, float] | None = None,
        same_source: bool = False,
        target: EmbeddedCloud | None = None,
    ) -> NetworkLoop:
        """Encoder and keypoints of a batch of pairs of normalised working clouds: the loop before its first
        iteration (:class:`service.network_loop.NetworkLoop`; :meth:`run_network` runs it to the end).

        ``src_n [B, N, 3]``, ``tgt_n [M, 3]`` (shared by every source, embedded once) or ``[B, M, 3]``. One
        encoder call when ``N == M`` (else one per side); keypoints are chosen per cloud (embeddings change
        with rotation). ``same_source``: the B sources are rigid copies of one cloud and share its k-NN graph.
        ``target``: :meth:`embed_cloud` of ``tgt_n [M, 3]``, when the caller runs it against many sources.
        Records ``timing["encoder"]``, and the keypoint selection in ``timing["iterations"]``.
        """
        timing = {} if timing is None else timing
        src_b = src_n  # [B, N, 3]
        tgt_b = tgt_n[None] if tgt_n.ndim == 2 else tgt_n  # [1 or B, M, 3]
        if src_b.ndim != 3 or tgt_b.ndim != 3 or len(tgt_b) not in (1, len(src_b)):
            raise ValueError(f"run_network: source {src_n.shape} and target {tgt_n.shape} do not batch")
        B, N, M = src_b.shape[0], src_b.shape[1], tgt_b.shape[1]
        if target is not None and (len(tgt_b) != 1 or target.scores.shape != (1, M)):
            raise ValueError(f"run_network: target embedding {target.scores.shape} is not of target {tgt_n.shape}")
        t1 = time.perf_counter()
        nb_s = nb_t = None
        if self.encoder_takes_neighbours:
            # rigid copies of one source (the rotation search) share its k-NN graph
            nb_s = np.repeat(self.neighbours(src_b[:1]), B, axis=0) if same_source else self.neighbours(src_b)
            nb_t = self.neighbours(tgt_b) if target is None else None
        if target is not None:
            (emb_s, score_s), emb_t, score_t = self.embed(src_b, nb_s), target.embedding, target.scores
        elif N == M:  # one batched encoder call
            both = np.concatenate([nb_s, nb_t]) if nb_s is not None else None
            emb, score = self.embed(np.concatenate([src_b, tgt_b]), both)
            emb_s, score_s, emb_t, score_t = emb[:B], score[:B], emb[B:], score[B:]
        else:
            (emb_s, score_s), (emb_t, score_t) = self.embed(src_b, nb_s), self.embed(tgt_b, nb_t)
        t2 = time.perf_counter()
        timing["encoder"] = timing.get("encoder", 0.0) + 1000 * (t2 - t1)

        kp_s = np.stack([top_k(s, min(keypoints, N)) for s in score_s])  # [B, K]
        kp_t = np.stack([top_k(s, min(keypoints, M)) for s in score_t])  # [1 or B, L]
        L = kp_t.shape[1]
        fs = gather_rows(emb_s, kp_s)  # [B, K, D]
        ft = np.ascontiguousarray(np.broadcast_to(gather_rows(emb_t, kp_t), (B, L, emb_t.shape[-1])))  # [B, L, D]
        loop = NetworkLoop(
            match=self.match,
            centroid=self.centroid,
            src_kp=kp_s,
            tgt_kp=np.ascontiguousarray(np.broadcast_to(kp_t, (B, L))),
            ps=gather_rows(src_b, kp_s).astype(np.float64),
            pt=np.ascontiguousarray(np.broadcast_to(gather_rows(tgt_b, kp_t), (B, L, 3))),
            fs=fs,
            ft=ft,
            emb_dist=embedding_distance(fs, ft) if self.matcher_takes_distance else None,  # [B, K, L], once
            rotation=np.broadcast_to(np.eye(3), (B, 3, 3)),
            translation=np.zeros((B, 3)),
            cumulative=[],
            min_gap=np.full(B, np.inf),
            median_gap=np.full(B, np.inf),
        )
        timing["iterations"] = timing.get("iterations", 0.0) + 1000 * (time.perf_counter() - t2)
        return loop

    def run_network(
        self,
        src_n: np.ndarray,
        tgt_n: np.ndarray,
        iterations: int,
        keypoints: int,
        timing: dict[str, float] | None = None,
        same_source: bool = False,
        target: EmbeddedCloud | None = None,
    ) -> NetworkOutput | list[NetworkOutput]:
        """The network loop on normalised working clouds (float32), for one pair or a batch of B.

        ``src_n`` is ``[N, 3]`` (one pair: returns a :class:`NetworkOutput`) or ``[B, N, 3]`` (B
        hypotheses: returns a list of B); ``tgt_n``, ``same_source`` and ``target`` as in
        :meth:`start_network`; one matcher call of batch B per iteration.
        """
        timing = {} if timing is None else timing
        for stage in ("encoder", "iterations", "svd"):  # this call's own figures
            timing[stage] = 0.0
        single = src_n.ndim == 2
        loop = self.start_network(src_n[None] if single else src_n, tgt_n, keypoints, timing, same_source, target)
        loop.advance(iterations, timing)
        outputs = loop.outputs()
        return outputs[0] if single else outputs

    # -- the pipeline ----------------------------------------------------------------------------
    def check_options(
        self,
        iterations: int | None,
        keypoints: int | None,
        working_size: int,
        refine: str | None,
        refine_points: int | None = None,
    ) -> tuple[int, int]:
        n_iter = self.default_iterations if iterations is None else int(iterations)
        if not 1 <= n_iter <= MAX_ITERATIONS:
            raise InputError(f"iterations must be in 1..{MAX_ITERATIONS}, got {n_iter}")
        if not MIN_POINTS <= working_size <= 4096:
            raise InputError(f"working_size must be in {MIN_POINTS}..4096, got {working_size}")
        k = self.default_keypoints if keypoints is None else int(keypoints)
        if not KEYPOINT_RANGE[0] <= k <= KEYPOINT_RANGE[1]:
            raise InputError(f"keypoints must be in {KEYPOINT_RANGE[0]}..{KEYPOINT_RANGE[1]}, got {k}")
        if k > working_size:
            raise InputError(f"keypoints ({k}) cannot exceed the working size ({working_size})")
        if (refine or "none") not in REFINE_MODES:
            raise InputError(f"refine must be one of {REFINE_MODES}, got {refine!r}")
        low, high = REFINE_POINTS_RANGE
        if refine_points is not None and not low <= int(refine_points) <= high:
            raise InputError(f"refine_points must be in {low}..{high}, got {refine_points}")
        return n_iter, k

    def register(
        self,
        source,
        target,
        iterations: int | None = None,
        keypoints: int | None = None,
        refine: str | None = None,
        initial_transform=None,
        working_size: int = DEFAULT_WORKING_SIZE,
        return_iterations: bool = False,
        icp_max_distance: float | None = None,
        icp_max_iterations: int = 30,
        rotation_search: SearchMode = False,
        search_rotations: int = 24,
        refine_points: int | None = None,
        drop_isolated: bool = True,
    ) -> RegistrationResult:
        """Pose ``src_to_tgt`` of ``source [N, 3]`` onto ``target [M, 3]`` (caller's units).

        ``rotation_search=True`` starts the network from ``search_rotations`` initial rotations of the
        source about its centroid (:mod:`service.rotation_search`: 24 or 60), all in one batched
        encoder call and one matcher call per iteration, keeps the hypothesis whose pose has the
        highest inlier ratio on the working clouds (ties: lower residual), then refines it. With
        ``refine="icp"`` every hypothesis first gets a short wide-basin ICP (``SEARCH_ICP_*``) and
        the ranking uses those poses (with an early-training network the raw poses rarely land
        close enough to rank the right basin first; ``docs/ROTATION_SEARCH.md``); the winner then
        gets the usual ICP (mutual nearest neighbours, ``icp_max_distance``) to convergence.
        ``refine="icp-plane"`` refines with point-to-plane ICP instead (:func:`service.icp.refine_plane`: a
        wide-basin robust symmetric stage at 3x the distance, then reciprocal point-to-plane at
        ``icp_max_distance``; each stage at most ``icp_max_iterations``): much closer than point-to-point
        between independently sampled scans (``docs/DESIGN.md``, "Refinement"). With the
        rotation search the per-hypothesis short ICPs stay point-to-point. With any refinement the search
        returns its ``SEARCH_KEEP`` best hypotheses; each distinct one gets a short refinement (``refine``'s stages
        with at most ``CANDIDATE_ITERATIONS`` updates each), they are ranked again on the working clouds, and the
        winner gets the full refinement. With any refinement, a model whose manifest has a ``search`` section
        (those trained on independently sampled pairs) searches on that many points spread evenly through each
        working cloud's rows with at most that many keypoints, and the winner is refined on the full clouds;
        its correspondences are then those of the subsample (that many).
        ``refine="icp-plane-multistart"`` then turns the refined pose by
        +-15 and +-30 degrees about each axis, moves each turn with a short ICP and keeps the best fit by
        a two-way point-to-plane score, refined again (:mod:`service.multistart`). When a refinement
        stops on a degenerate system (too few pairs, a planar or linear target) it keeps the pose it had
        and adds a warning; ``reliable`` still comes from :func:`service.quality.assess` alone.
        ``drop_isolated`` (default): isolated points -- flying pixels, sparse clutter; a mean distance to their
        8 nearest others above 3x the cloud's median (:func:`service.sampling.isolated_points`) -- are left
        out of the working and refinement clouds, so the network and the refinement see the surfaces
        (``docs/ACCURACY.md``, "Outliers"); returned indices never point at them.
        ``refine_points``: the refinement moves up to this many points of the caller's source onto up to this
        many target points (every point up to that many, else one per voxel: :func:`service.sampling.spread_indices`)
        instead of the working clouds; more points give a more precise pose on dense scans at a
        higher cost (``docs/ACCURACY.md``, "Refinement on more points"). ``quality`` stays measured on the
        working clouds. Ignored without refinement.
        ``timing_ms["search"]`` is the whole search (network, short ICPs, ranking) and
        ``timing_ms["search_per_hypothesis"]`` that divided by the number of hypotheses.

        ``rotation_search="auto"`` runs the plain registration (with ``refine``) first and returns it
        unchanged unless it looks wrong (:func:`needs_search`: an inlier ratio below
        ``AUTO_SEARCH_RELATIVE_RATIO`` of what the target's density allows) and neither working cloud is
        degenerate (identical or collinear points: no start rotation can fix what they leave open); then it
        runs the rotation search as above on the same working clouds and returns whichever of the two final poses
        :func:`service.rotation_search.rank_hypotheses`
        ranks first (inlier ratio, then residual; the plain one on a tie). The stage keys of ``timing_ms``
        are the plain pass's; ``"search"`` (the whole second pass: hypotheses, short ICPs, ranking, the
        winner's refinement and quality, the final comparison) and ``"search_per_hypothesis"`` are present
        exactly when the search ran; ``"total"`` covers both.
        """
        t0 = time.perf_counter()
        timing: dict[str, float] = {}
        src = check_cloud(source, "source")
        tgt = check_cloud(target, "target")
        n_iter, k = self.check_options(iterations, keypoints, working_size, refine, refine_points)
        mode = search_mode(rotation_search)
        hypotheses = search_rotations_for(int(search_rotations)) if mode != "off" else None
        R_init, t_init = np.eye(3), np.zeros(3)
        if initial_transform is not None:
            R_init, t_init = check_transform(initial_transform)
        src_moved = src @ R_init.T + t_init  # [N, 3] source in the initial guess's frame

        idx_s = resample_indices(src_moved, working_size, drop_isolated)  # [Ns] into the caller's source
        idx_t = resample_indices(tgt, working_size, drop_isolated)  # [Nt]
        src_w, tgt_w = src_moved[idx_s], tgt[idx_t]
        src_r, tgt_r = src[idx_s], tgt_w  # the refinement's clouds: the working ones unless refine_points
        if refine_points is not None and (refine or "none") != "none":
            src_r = src[spread_indices(src_moved, int(refine_points), drop_isolated)]  # [Nr, 3]
            tgt_r = tgt[spread_indices(tgt, int(refine_points), drop_isolated)]  # [Mr, 3]
        norm = Normalization.fit(src_w, tgt_w, self.reference_radius)
        src_n, tgt_n = norm.apply_src(src_w).astype(np.float32), norm.apply_tgt(tgt_w).astype(np.float32)
        work = _Working(src, idx_s, idx_t, tgt_w, src_r, tgt_r, norm, src_n, tgt_n, R_init, t_init)
        timing["preprocess"] = 1000 * (time.perf_counter() - t0)
        options = {"iterations": n_iter, "keypoints": k, "refine": refine or "none",
                   "return_iterations": return_iterations, "icp_max_distance": icp_max_distance,
                   "icp_max_iterations": icp_max_iterations}

        result = self._solve(work, hypotheses if mode == "on" else None, timing, **options)
        if (mode == "auto" and not degenerate(src_w) and not degenerate(tgt_w)
                and needs_search(result, attainable_inlier_ratio(tgt_w, INLIER_DISTANCE * norm.scale))):
            assert hypotheses is not None
            started = time.perf_counter()
            searched = self._solve(work, hypotheses, {}, **options)
            rotations = np.stack([result.rotation, searched.rotation])  # [2, 3, 3] plain first: it wins ties
            translations = np.stack([result.translation, searched.translation])  # [2, 3]
            order = rank_hypotheses(src[idx_s], tgt_w, rotations, translations, INLIER_DISTANCE * norm.scale)[0]
            if order[0] == 1:  # the search's winner fits better; keep the plain pass's stage timings
                searched.timing_ms = timing
                result = searched
            timing["search"] = 1000 * (time.perf_counter() - started)
            timing["search_per_hypothesis"] = timing["search"] / len(hypotheses)
        timing["total"] = 1000 * (time.perf_counter() - t0)
        return result

    def _solve(
        self,
        work: _Working,
        hypotheses: np.ndarray | None,
        timing: dict[str, float],
        iterations: int,
        keypoints: int,
        refine: str,
        return_iterations: bool,
        icp_max_distance: float | None,
        icp_max_iterations: int,
    ) -> RegistrationResult:
        """Network (plain, or the rotation search over ``hypotheses``), refinement and quality on ``work``."""
        norm, src, idx_s, tgt_w = work.norm, work.src, work.idx_s, work.tgt_w
        net_s, net_t = idx_s, work.idx_t  # the caller's rows of the clouds the network ran on
        if hypotheses is None:
            net = self.run_network(work.src_n, work.tgt_n, iterations, keypoints, timing)
            candidates = [SearchCandidate(net, np.eye(3), net.rotation, net.translation)]
        else:
            short_icp = refine != "none"  # point-to-point for every refine mode (docs/DESIGN.md)
            tic = time.perf_counter()
            sub_s, sub_t = np.arange(len(work.src_n)), np.arange(len(work.tgt_n))
            subsample = self.manifest.search_subsample
            if short_icp and subsample:  # the refinement restores the precision: search a subsample
                sub_s, sub_t = (evenly_spaced_indices(len(c), subsample[0]) for c in (work.src_n, work.tgt_n))
                keypoints = min(keypoints, subsample[1], len(sub_s), len(sub_t))
            src_n, tgt_n = work.src_n[sub_s], work.tgt_n[sub_t]  # [Ns', 3], [Nt', 3]
            net_s, net_t = idx_s[sub_s], work.idx_t[sub_t]
            target = self.embed_cloud(tgt_n)  # once for every hypothesis
            timing["encoder"] = 1000 * (time.perf_counter() - tic)
            candidates = search_hypotheses(
                partial(self.start_network, target=target), src_n, tgt_n, hypotheses, iterations, keypoints,
                short_icp, INLIER_DISTANCE, timing,
            )
            # with a refinement every distinct kept candidate is refined and the refined poses ranked again
            candidates = distinct_candidates(candidates) if short_icp else candidates[:1]
        t3 = time.perf_counter()
        starts = [self._to_caller(norm, c.rotation, c.translation, work.R_init, work.t_init) for c in candidates]
        scale = norm.scale
        refine_warnings: tuple[str, ...] = ()
        pick, ambiguity = 0, None
        R_final, t_final = starts[0]
        surface: Surface | None = None  # the refinement's target surface (icp-plane modes)
        if refine != "none":
            distance = icp_max_distance if icp_max_distance is not None else ICP_DISTANCE * scale
            surface = Surface.of(work.tgt_r) if refine != "icp" else None  # one target surface for every stage
            if len(starts) > 1:  # search candidates: a short refinement of each, ranked, then the winner's full one
                basins = [self._refine(work, R0, t0, refine, distance, CANDIDATE_ITERATIONS, surface)
                          for R0, t0 in starts]  # short refinements: enough to rank the basins
                rotations = np.stack([b.rotation for b in basins])  # [C, 3, 3]
                order, ratios, _ = rank_hypotheses(src[idx_s], tgt_w, rotations,
                                                   np.stack([b.translation for b in basins]), INLIER_DISTANCE * scale)
                pick = int(order[0])
                ambiguity = ambiguity_warning(rotations, ratios, pick)
                R_final, t_final = basins[pick].rotation, basins[pick].translation
            refined = self._refine(work, R_final, t_final, refine, distance, icp_max_iterations, surface)
            if refine == "icp-plane-multistart":
                R_turn, t_turn, start = best_turned_pose(
                    work.src_r, work.tgt_r, refined.rotation, refined.translation, scale, surface
                )
                if start:  # a turned start fits better: the precise stage only (the wide one could pull it back)
                    refined = icp_plane(work.src_r, work.tgt_r, R_turn, t_turn, max_distance=distance,
                                        max_iterations=icp_max_iterations, target_surface=surface)
            R_final, t_final, refine_warnings = refined.rotation, refined.translation, refined.warnings
            timing["refine"] = 1000 * (time.perf_counter() - t3)
        net, R_start = candidates[pick].output, candidates[pick].start
        poses = [
            IterationPose(*self._to_caller(norm, R @ R_start, t, work.R_init, work.t_init))
            for R, t in (net.cumulative if return_iterations else [])
        ]
        t4 = time.perf_counter()
        working = surface if surface is not None and work.tgt_r is tgt_w else None  # the working target's normals
        tree = KDTree(tgt_w) if working is None else working.tree  # shared by the two checks below
        quality = assess(src[idx_s], tgt_w, R_final, t_final, INLIER_DISTANCE * scale, tree)
        stability = pose_stability(src[idx_s] @ R_final.T + t_final, tgt_w, tree, ICP_DISTANCE * scale, working)
        weak = weak_motion_warning(stability)
        weights = net.weights
        w_sum = weights.sum()
        result = RegistrationResult(
            rotation=R_final,
            translation=t_final,
            source_index=net_s[net.src_kp].astype(np.int64),
            target_index=net_t[net.tgt_kp[net.matched]].astype(np.int64),
            credibility=net.credibility.astype(np.float32),
            weight=(weights / (w_sum + 1e-8) if w_sum > 0 else np.full_like(weights, 1 / len(weights))).astype(
                np.float32
            ),
            inlier_ratio=quality.inlier_ratio,
            residual_rms=quality.residual_rms,
            reliable=bool(quality.reliable) and ambiguity is None and weak is None,  # assess(): degenerate clouds
            warnings=[*quality.warnings, *refine_warnings, *(w for w in (ambiguity, weak) if w)],
            stability=None if stability is None else stability.eigenvalue,
            iterations=iterations,
            timing_ms=timing,
            iteration_poses=poses,
        )
        timing["postprocess"] = 1000 * (time.perf_counter() - t4)
        return result

    @staticmethod
    def _refine(work: _Working, R0: np.ndarray, t0: np.ndarray, refine: str, distance: float,
                max_iterations: int, surface: Surface | None) -> IcpResult:
        """``refine`` (``icp`` or the point-to-plane stages of ``icp-plane*``) of the caller's pose ``R0, t0``."""
        if refine == "icp":
            return icp(work.src_r, work.tgt_r, R0, t0, max_distance=distance, max_iterations=max_iterations)
        return refine_plane(work.src_r, work.tgt_r, R0, t0, max_distance=distance, max_iterations=max_iterations,
                            target_surface=surface)

    @staticmethod
    def _to_caller(norm: Normalization, R: np.ndarray, t: np.ndarray, R_init: np.ndarray, t_init: np.ndarray):
        """Pose between normalised clouds -> caller's ``src_to_tgt``, composed after the initial guess."""
        R_c, t_c = norm.unnormalize_pose(R, t)
        return compose(R_c, t_c, R_init, t_init)


def check_transform(matrix) -> tuple[np.ndarray, np.ndarray]:
    """A 4x4 rigid ``src_to_tgt`` guess -> ``(R, t)``; rejects non-rigid or non-finite matrices."""
    T = np.asarray(matrix, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"initial_transform must be 4x4, got {list(T.shape)}")
    if not np.isfinite(T).all():
        raise InputError("initial_transform contains NaN or infinite values")
    R, t = T[:3, :3], T[:3, 3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError("initial_transform must be rigid: orthonormal rotation with det +1 and last row 0 0 0 1")
    return R, t
