"""The registration pipeline: ONNX Runtime for the networks, numpy for everything else.

``Registrar.register`` runs the stages of :mod:`service.stages`: validate -> anchor (each cloud about its own
centroid) -> sample (working clouds) -> normalise -> network (encoder, top-K keypoints, n x (matcher -> argmax ->
credibility weights -> weighted SVD -> compose)) or the rotation search -> refine (optional ICP, point-to-point or
point-to-plane) -> assess (quality) -> fine refinement of the result kept (dense clouds) -> the pose back in the
caller's frames.
This module holds the model's sessions and the network calls the network and search stages make.
"""

from __future__ import annotations

import math
import os
import threading
import time
from contextlib import nullcontext
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import onnxruntime as ort
from numpy.typing import ArrayLike

from service.blas_threads import use_one_blas_thread
from service.bounded_runs import ENCODE_POINTS_PER_CALL, MATCH_PAIRS_PER_CALL, run_bounded, share_one_cpu_arena
from service.checks import MIN_POINTS, check_cloud, check_transform
from service.errors import InputError
from service.manifest import Manifest, ModelIntegrityError, load_manifest
from service.neighbours import knn_graph
from service.network_loop import NetworkLoop, NetworkOutput, gather_rows
from service.options import (
    DEFAULT_WORKING_SIZE,
    KEYPOINT_RANGE,
    MAX_ITERATIONS,
    RegistrationOptions,
    SearchMode,
    search_mode,
)
from service.result import IterationPose, RegistrationResult
from service.selection import top_k
from service.speculation import Helpers, Speculation, check, shared_helpers
from service.stages.features import DESCRIBE_BELOW, describable, feature_confirmed
from service.stages.guess import (
    better_than_unguessed,
    better_unrefined,
    doubtful_with_guess,
    keeps_guess,
    same_basin,
)
from service.stages.network import Candidates
from service.stages.normalise import ICP_DISTANCE, INLIER_DISTANCE, Working, to_caller
from service.stages.pipeline import Stages
from service.stages.refine import CANDIDATE_ITERATIONS, icp_distance
from service.stages.search import (
    AUTO_SEARCH_RELATIVE_RATIO,
    SEARCH_AHEAD_BELOW,
    looks_wrong,
    needs_search,
    plain_overlay,
    retry_points,
    searched_ahead,
)
from service.stages.validate import Request

__all__ = [  # the names callers import from here, wherever they live now
    "AUTO_SEARCH_RELATIVE_RATIO", "CANDIDATE_ITERATIONS", "DEFAULT_WORKING_SIZE", "ICP_DISTANCE", "INLIER_DISTANCE",
    "KEYPOINT_RANGE", "MAX_ITERATIONS", "MIN_POINTS", "EmbeddedCloud", "InputError", "IterationPose", "Registrar",
    "RegistrationOptions", "RegistrationResult", "SearchMode", "Stages", "check_cloud", "check_transform",
    "default_threads", "embedding_distance", "needs_search", "search_mode", "session_options", "top_k",
]


def default_threads() -> int:
    return max(1, min(2, os.cpu_count() or 1))


def embedding_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``||a_i - b_j||`` ``[B, K, L]`` (float32) of embeddings ``a [B, K, D]``, ``b [B, L, D]``.

    Computed as ``|a|^2 + |b|^2 - 2 a.b`` in float64: the cancellation error (~1e-16 |a|^2) is far
    below float32 rounding, so the result agrees with an explicit-difference float32 distance.
    """
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    d2 = (a64 * a64).sum(-1)[:, :, None] + (b64 * b64).sum(-1)[:, None, :] - 2.0 * (a64 @ b64.transpose(0, 2, 1))
    return np.sqrt(np.maximum(d2, 0.0)).astype(np.float32)


@dataclass(frozen=True)
class EmbeddedCloud:
    """A working cloud's encoder output, reused across network runs (the rotation search's target)."""

    embedding: np.ndarray  # [1, M, D]
    scores: np.ndarray  # [1, M] keypoint significance


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
    return share_one_cpu_arena(options)  # one arena for every session: bounded by the largest call (bounded_runs)


class Registrar:
    """One loaded, hash-verified model: an ONNX Runtime session per graph, shared by all callers.

    Built on the main thread, it also sets numpy's BLAS to one thread for the process
    (:func:`service.blas_threads.use_one_blas_thread`): ONNX Runtime's threads own the cores.
    """

    option_names = RegistrationOptions.names()  # what register() takes as keyword overrides

    def __init__(self, model_dir: str | Path, threads: int | None = None, warmup: bool = True,
                 stages: Stages | None = None, helpers: Helpers | None = None):
        use_one_blas_thread()
        self.stages = Stages() if stages is None else stages  # what register() runs (service.stages.pipeline)
        self.manifest: Manifest = load_manifest(model_dir)
        self.name = self.manifest.name
        self.config = self.manifest.config
        self.reference_radius = float(self.manifest.normalization.get("reference_radius", 1.0))
        self.centroid = self.config.get("centroid", "weighted")
        threads = threads or default_threads()
        # spare cores run the search of "auto" ahead (service.speculation); one thread: none
        self.helpers = (helpers or shared_helpers(default_threads())) if threads > 1 else None
        options = session_options(threads)
        providers = ["CPUExecutionProvider"]
        started = time.perf_counter()
        self.encoder = ort.InferenceSession(self.manifest.graph_bytes("encoder"), options, providers=providers)
        self.matchers = [
            ort.InferenceSession(self.manifest.graph_bytes(role), options, providers=providers)
            for role in self.manifest.matcher_roles
        ]
        neighbours = next((i for i in self.encoder.get_inputs() if i.name == "neighbours"), None)
        self.encoder_takes_neighbours = neighbours is not None
        self.matcher_takes_distance = any(i.name == "emb_dist" for i in self.matchers[0].get_inputs())
        self.knn = int(self.config.get("knn", 12))
        if neighbours is not None and isinstance(neighbours.shape[-1], int) and neighbours.shape[-1] != self.knn:
            raise ModelIntegrityError(f"model {self.name!r}: config knn {self.knn}, but its encoder graph takes "
                                      f"{neighbours.shape[-1]} neighbours per point")
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
        per_row = feeds["points"].shape[1]  # N points per row of [B, N, 3]
        emb, score = run_bounded(self.encoder, feeds, per_row, ENCODE_POINTS_PER_CALL)
        return emb, score

    def embed_cloud(self, points: np.ndarray) -> EmbeddedCloud:
        """The encoder output of one working cloud ``[M, 3]`` (float32), for :meth:`run_network`'s ``target``."""
        cloud = points[None]  # [1, M, 3]
        neighbours = self.neighbours(cloud) if self.encoder_takes_neighbours else None
        return EmbeddedCloud(*self.embed(cloud, neighbours))

    def match(self, iteration: int, src_xyz: np.ndarray, tgt_xyz: np.ndarray, src_emb: np.ndarray,
              tgt_emb: np.ndarray, emb_dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
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
        pairs = src_xyz.shape[1] * tgt_xyz.shape[1]  # K x L per row
        scores, logit = run_bounded(session, feeds, pairs, MATCH_PAIRS_PER_CALL)
        return scores, logit

    def start_network(
        self,
        src_n: np.ndarray,
        tgt_n: np.ndarray,
        keypoints: int,
        timing: dict[str, float] | None = None,
        same_source: bool = False,
        target: EmbeddedCloud | None = None,
        graphs: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> NetworkLoop:
        """Encoder and keypoints of a batch of pairs of normalised working clouds: the loop before its first
        iteration (:class:`service.network_loop.NetworkLoop`; :meth:`run_network` runs it to the end).

        ``src_n [B, N, 3]``, ``tgt_n [M, 3]`` (shared by every source, embedded once) or ``[B, M, 3]``. One
        encoder call when ``N == M`` (else one per side); keypoints are chosen per cloud (embeddings change
        with rotation). ``same_source``: the B sources are rigid copies of one cloud and share its k-NN graph.
        ``target``: :meth:`embed_cloud` of ``tgt_n [M, 3]``, when the caller runs it against many sources.
        ``graphs``: one pair's clouds' nearest rows, ``[N, K]`` and ``[M, K]`` with ``K >= knn``, nearest first
        (itself included), when the caller has them (:attr:`service.stages.normalise.Working.working_graphs`).
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
        if self.encoder_takes_neighbours and graphs is not None and B == 1 and target is None:
            nb_s, nb_t = (graph[None, :, : self.knn] for graph in graphs)  # [1, N, knn], [1, M, knn]
        elif self.encoder_takes_neighbours:
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
        graphs: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> NetworkOutput | list[NetworkOutput]:
        """The network loop on normalised working clouds (float32), for one pair or a batch of B.

        ``src_n`` is ``[N, 3]`` (one pair: returns a :class:`NetworkOutput`) or ``[B, N, 3]`` (B
        hypotheses: returns a list of B); ``tgt_n``, ``same_source``, ``target`` and ``graphs`` as in
        :meth:`start_network`; one matcher call of batch B per iteration.
        """
        timing = {} if timing is None else timing
        for stage in ("encoder", "iterations", "svd"):  # this call's own figures
            timing[stage] = 0.0
        single = src_n.ndim == 2
        loop = self.start_network(src_n[None] if single else src_n, tgt_n, keypoints, timing, same_source, target,
                                  graphs)
        loop.advance(iterations, timing)
        outputs = loop.outputs()
        return outputs[0] if single else outputs

    # -- the pipeline ----------------------------------------------------------------------------
    def check_options(self, iterations: int | None, keypoints: int | None, working_size: int, refine: str | None,
                      refine_points: int | None = None) -> tuple[int, int]:
        """The network's ``(iterations, keypoints)`` for these options (the model's defaults filled in), or
        ``InputError`` naming the first bad one."""
        options = RegistrationOptions(iterations=iterations, keypoints=keypoints, working_size=working_size,
                                      refine=refine, refine_points=refine_points)
        return options.network(self.default_iterations, self.default_keypoints)

    def register(self, source: ArrayLike, target: ArrayLike, options: RegistrationOptions | None = None,
                 **overrides) -> RegistrationResult:
        """Pose ``src_to_tgt`` of ``source [N, 3]`` onto ``target [M, 3]`` (caller's units).

        ``options`` (default: all defaults) with keyword ``overrides`` of its fields, e.g.
        ``register(src, tgt, refine="icp-plane")``; :class:`service.options.RegistrationOptions` says what each
        does. ``timing_ms`` has a key per stage (``preprocess``, ``encoder``, ``iterations``, ``svd``, ``refine``,
        ``postprocess``), ``search`` / ``search_per_hypothesis`` when the rotation search ran, and ``total``.
        """
        with self.helpers.registering() if self.helpers is not None else nullcontext():
            return self._register(source, target, options, overrides)

    def _register(self, source: ArrayLike, target: ArrayLike, options: RegistrationOptions | None,
                  overrides: dict) -> RegistrationResult:
        t0 = time.perf_counter()
        timing: dict[str, float] = {}
        stages = self.stages
        request = stages.validate(source, target, options, overrides, self.default_iterations, self.default_keypoints)
        request, anchors = stages.anchor(request)  # every later stage works on clouds about the origin
        work = stages.normalise(stages.sample(request), self.reference_radius)
        timing["preprocess"] = 1000 * (time.perf_counter() - t0)
        mode = request.options.search
        if mode == "on":
            result = self.solve(work, request, request.hypotheses, timing)
        else:
            found = self.plain_candidates(work, request, timing)
            overlay = plain_overlay(work, found) if mode == "auto" else math.inf  # how well the plain pose overlays
            describe = request.options.refine_mode != "none"
            if overlay < SEARCH_AHEAD_BELOW and describe:  # a turned scan, mostly: a feature candidate beside it
                found = stages.features(self, work, found, request.iterations, request.keypoints, timing)
            # the search ahead only where the network's pose is the only candidate
            ahead = self.search_ahead(work, request) if overlay < SEARCH_AHEAD_BELOW and len(found.poses) == 1 else None
            try:
                result = self.solve(work, request, None, timing, found=found)
                if (SEARCH_AHEAD_BELOW <= overlay < DESCRIBE_BELOW and describe and describable(work)
                        and looks_wrong(work, result)):
                    # a passable plain pose refined into a doubtful result: a feature candidate before the search
                    more = stages.features(self, work, found, request.iterations, request.keypoints, timing)
                    if len(more.poses) > len(found.poses):
                        found, result = more, self.solve(work, request, None, timing, found=more)
                strayed = False  # a result that does not keep the caller's guess and that the unguessed pose denies
                if request.options.initial_transform is not None and (not keeps_guess(work, result)
                                                                      or doubtful_with_guess(result)):
                    result, strayed = self.beside_unguessed(work, request, result, timing)
                if mode == "auto":  # the search only when the plain result looks wrong
                    solve = searched_ahead(partial(self.solve, work, request), ahead)
                    guided = request.options.initial_transform is not None and keeps_guess(work, result)
                    result = stages.auto_search(solve, work, result, request.hypotheses, timing,
                                                retry_points(self.manifest.search_subsample),
                                                confirmed=feature_confirmed(work, found, result), guided=guided,
                                                strayed=strayed)
            finally:
                if ahead is not None:
                    ahead.cancel()  # no-op when its result was taken
        result = stages.fine(work, result, request.options, timing)  # the chosen pose, on denser clouds
        result = stages.free_space(work, result, request.options, timing)  # reliable: no surface through free space
        result = stages.symmetry(work, result, request.options, timing)  # reliable: no half turn fits as well
        if mode == "auto":  # a doubtful result against the pose the descriptors agree on, checked as any result
            agreed = stages.consensus(self, work, result, request.options, request.iterations, request.keypoints,
                                      timing)
            if agreed is not result:  # refined on the 2,048-point fine clouds only: the fine stage as well
                agreed = stages.fine(work, agreed, request.options, timing)
                result = stages.symmetry(work, stages.free_space(work, agreed, request.options, timing),
                                         request.options, timing)
        result = stages.unrefined_check(work, result, request.options, timing)  # refine "none": a refinement leaves it
        result = anchors.result_to_caller(result)
        result = stages.guess_check(work, result, request, self.reference_radius)  # a warning far from the guess
        result = stages.scale_check(work, result)  # a warning where the clouds' sizes differ as units do
        result = stages.float32_check(work, result, request)  # a warning where float32 rounds coordinates coarsely
        timing["total"] = 1000 * (time.perf_counter() - t0)
        return result

    def plain_candidates(self, work: Working, request: Request, timing: dict[str, float]) -> Candidates:
        """The plain network's pose (stage ``network``) and, where the caller gave one, the guess (``with_guess``)."""
        return self.with_guess(work, request, self.stages.network(self, work, request.iterations, request.keypoints,
                                                                  timing))

    def beside_unguessed(self, work: Working, request: Request, result: RegistrationResult,
                         timing: dict[str, float]) -> tuple[RegistrationResult, bool]:
        """The plain ``result`` of a request whose guess it does not keep (or keeps, not ``reliable``), against the
        network's pose from the caller's own frame (stage ``unguessed``: the request's start without the guess), refined
        (as the request asks; unrefined with ``refine: "none"``) and assessed alone as that request's plain pass does,
        unless ``result`` lies in its basin (:func:`service.stages.guess.better_than_unguessed`; unrefined,
        :func:`service.stages.guess.better_unrefined`, or where ``result`` keeps the guess, that pose only if it is
        ``reliable``); and whether ``auto`` should search the result kept although it
        may look right: it is the guessed one, that pose lies elsewhere, and it looks wrong
        (:func:`service.stages.search.looks_wrong`), so the request without the guess searches; nothing but a wrong
        guess led to the result (``docs/decisions/0068-the-unguessed-start-competes.md``)."""
        o = request.options
        found = self.stages.unguessed(self, work, request.iterations, request.keypoints, timing)
        distance, pose = icp_distance(work, o), (result.rotation, result.translation)
        if found is None or same_basin(work, to_caller(work, found.poses[0].rotation, found.poses[0].translation), pose,
                                       distance):
            return result, False
        alone_timing: dict[str, float] = {}
        alone = self.solve(work, request, None, alone_timing, found=found)
        for stage in ("refine", "postprocess"):  # its refinement and assessment, beside the plain pass's
            if stage in alone_timing:  # refine "none" runs no refinement: no "refine" key
                timing[stage] = timing.get(stage, 0.0) + alone_timing[stage]
        if o.refine_mode == "none" and keeps_guess(work, result):  # doubtful: only a reliable pose replaces it
            kept, unconfirmed = (alone if alone.reliable else result), False  # (decision 0118)
        elif o.refine_mode == "none":  # unrefined poses: ranked by short refinements, as the guess is (decision 0117)
            started = time.perf_counter()
            kept, unconfirmed = better_unrefined(work, result, alone), False
            timing["postprocess"] = timing.get("postprocess", 0.0) + 1000 * (time.perf_counter() - started)
        else:
            kept, unconfirmed = better_than_unguessed(work, result, alone, distance)
        if kept is alone:
            kept.timing_ms = timing
        return kept, unconfirmed and looks_wrong(work, alone)  # where the request without the guess searches

    def with_guess(self, work: Working, request: Request, found: Candidates) -> Candidates:
        """``found`` (the plain network's or the search's candidates) and, where the caller gave an
        ``initial_transform``, that guess itself (stage ``guess``), should the network have moved a good guess away."""
        return found if request.options.initial_transform is None else self.stages.guess(work, found)

    def search_ahead(self, work: Working, request: Request) -> Speculation | None:
        """The search of ``rotation_search="auto"`` started in a helper thread beside the plain pass (where the plain
        network's pose overlays poorly, :func:`service.stages.search.plain_overlay`), when a core is free
        (:class:`service.speculation.Helpers`); else ``None``."""
        if self.helpers is None:
            return None
        return self.helpers.start(
            lambda cancelled: self.solve(work, request, request.hypotheses, {}, cancelled=cancelled))

    def solve(self, work: Working, request: Request, hypotheses: np.ndarray | None, timing: dict[str, float],
              points: int | None = None, found: Candidates | None = None,
              cancelled: threading.Event | None = None) -> RegistrationResult:
        """Network (plain, or the rotation search from ``hypotheses [H, 3, 3]``, on ``points`` rows per cloud where
        given) -> refine -> slide check -> (after a search) flip check -> assess on ``work``. ``found``: the plain
        network's candidates, already run; ``cancelled``: once set, stop with
        :class:`service.speculation.CancelledError` at the next stage (work running ahead, :meth:`search_ahead`)."""
        stages, o = self.stages, request.options
        if hypotheses is None:
            if found is None:
                found = self.plain_candidates(work, request, timing)
        else:
            found = self.with_guess(work, request, stages.search(self, work, hypotheses, request.iterations,
                                                                 request.keypoints, o.refine_mode, timing, points))
        check(cancelled)
        started = time.perf_counter()
        refined = stages.refine(work, [to_caller(work, c.rotation, c.translation) for c in found.poses], o)
        check(cancelled)
        refined = stages.slide(work, refined, o)
        if hypotheses is not None:  # a searched pose turned half a turn from the truth (docs/decisions/0016)
            check(cancelled)
            refined = stages.flip(work, refined, o)
        elapsed = 1000 * (time.perf_counter() - started)
        if o.refine_mode != "none":
            timing["refine"] = elapsed
        result = stages.assess(work, found, refined, request.iterations, o.return_iterations, timing,
                               unrefined=o.refine_mode == "none")
        if o.refine_mode == "none":  # the short refinements that rank a guess (decision 0117): a check, no refinement
            timing["postprocess"] = timing.get("postprocess", 0.0) + elapsed
        return result
