"""The registration pipeline: ONNX Runtime for the networks, numpy for everything else.

``Registrar.register`` = validate -> resample to the working size -> similarity normalisation ->
encoder -> top-K keypoints -> n x (matcher -> argmax -> credibility weights -> weighted SVD ->
compose) -> back to the caller's units -> optional ICP -> quality record.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from service.icp import icp
from service.manifest import Manifest, load_manifest
from service.normalization import Normalization
from service.procrustes import compose, to_matrix, weighted_procrustes
from service.quality import assess, degeneracy_warnings
from service.sampling import resample_indices

MIN_POINTS = 32
MAX_ITERATIONS = 8
KEYPOINT_RANGE = (16, 512)
DEFAULT_WORKING_SIZE = 768
INLIER_DISTANCE = 0.05  # normalised units (the paper's match threshold): quality inliers
ICP_DISTANCE = 0.1  # normalised units: default ICP correspondence distance
REFINE_MODES = ("none", "icp")


class InputError(ValueError):
    """A request the pipeline cannot run (bad shape, non-finite values, out-of-range option)."""


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


def lower_median_weights(credibility: np.ndarray) -> np.ndarray:
    """Credibilities at or above the lower median, others zeroed (``[K] -> [K]``)."""
    k = (len(credibility) - 1) // 2
    median = np.partition(credibility, k)[k]
    return credibility * (credibility >= median)


def top_k(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` highest ``scores [N]``, highest first (ties: lower index first)."""
    idx = np.argpartition(-scores, k - 1)[:k] if k < len(scores) else np.arange(len(scores))
    return idx[np.lexsort((idx, -scores[idx]))]


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

    @property
    def transform(self) -> np.ndarray:
        """``[4, 4]`` homogeneous src_to_tgt."""
        return to_matrix(self.rotation, self.translation)


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


class Registrar:
    """One loaded, hash-verified model: an ONNX Runtime session per graph, shared by all callers."""

    def __init__(self, model_dir: str | Path, threads: int | None = None, warmup: bool = True):
        self.manifest: Manifest = load_manifest(model_dir)
        self.name = self.manifest.name
        self.config = self.manifest.config
        self.reference_radius = float(self.manifest.normalization.get("reference_radius", 1.0))
        self.centroid = self.config.get("centroid", "weighted")
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads or default_threads()
        options.inter_op_num_threads = 1
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        providers = ["CPUExecutionProvider"]
        started = time.perf_counter()
        self.encoder = ort.InferenceSession(str(self.manifest.graphs["encoder"]), options, providers=providers)
        self.matchers = [
            ort.InferenceSession(str(f), options, providers=providers) for f in self.manifest.matcher_files
        ]
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
    def embed(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``[B, N, 3]`` float32 -> embeddings ``[B, N, D]``, scores ``[B, N]``."""
        emb, score = self.encoder.run(None, {"points": points.astype(np.float32, copy=False)})
        return emb, score

    def match(self, iteration: int, src_xyz, tgt_xyz, src_emb, tgt_emb) -> tuple[np.ndarray, np.ndarray]:
        """Matching scores ``[B, K, L]`` and credibility logits ``[B, K]`` of one iteration."""
        session = self.matchers[min(iteration, len(self.matchers) - 1)]
        feeds = {
            "src_xyz": src_xyz.astype(np.float32, copy=False),
            "tgt_xyz": tgt_xyz.astype(np.float32, copy=False),
            "src_emb": src_emb,
            "tgt_emb": tgt_emb,
        }
        scores, logit = session.run(None, feeds)
        return scores, logit

    def run_network(
        self,
        src_n: np.ndarray,
        tgt_n: np.ndarray,
        iterations: int,
        keypoints: int,
        timing: dict[str, float] | None = None,
    ) -> NetworkOutput:
        """The network loop on normalised working clouds ``[N, 3]``, ``[M, 3]`` (float32)."""
        timing = {} if timing is None else timing
        t1 = time.perf_counter()
        if len(src_n) == len(tgt_n):
            emb, score = self.embed(np.stack([src_n, tgt_n]))  # one batched encoder call
            emb_s, emb_t, score_s, score_t = emb[0], emb[1], score[0], score[1]
        else:
            (emb_s, score_s), (emb_t, score_t) = (tuple(a[0] for a in self.embed(c[None])) for c in (src_n, tgt_n))
        t2 = time.perf_counter()
        timing["encoder"] = 1000 * (t2 - t1)

        kp_s = top_k(score_s, min(keypoints, len(src_n)))  # [K]
        kp_t = top_k(score_t, min(keypoints, len(tgt_n)))  # [L]
        ps, pt = src_n[kp_s].astype(np.float64), tgt_n[kp_t]  # [K, 3], [L, 3]
        fs, ft = emb_s[kp_s][None], emb_t[kp_t][None]  # [1, K, D], [1, L, D]
        R_tot, t_tot = np.eye(3), np.zeros(3)
        svd_ms, cumulative, min_gap, median_gap = 0.0, [], np.inf, np.inf
        for it in range(iterations):
            scores, logit = self.match(it, ps[None], pt[None], fs, ft)
            tic = time.perf_counter()
            matched = scores[0].argmax(axis=1)  # [K]
            if scores.shape[2] > 1:
                top2 = np.partition(scores[0], -2, axis=1)[:, -2:]  # [K, 2]
                min_gap = min(min_gap, float((top2[:, 1] - top2[:, 0]).min()))
            credibility = 1.0 / (1.0 + np.exp(-logit[0].astype(np.float64)))  # [K]
            weights = lower_median_weights(credibility)
            below = credibility[weights == 0]
            if below.size:
                median_gap = min(median_gap, float(credibility[weights > 0].min() - below.max()))
            R, t = weighted_procrustes(ps, pt[matched].astype(np.float64), weights, self.centroid)
            ps = ps @ R.T + t
            R_tot, t_tot = compose(R, t, R_tot, t_tot)
            cumulative.append((R_tot, t_tot))
            svd_ms += 1000 * (time.perf_counter() - tic)
        timing["iterations"] = 1000 * (time.perf_counter() - t2) - svd_ms
        timing["svd"] = svd_ms
        return NetworkOutput(R_tot, t_tot, kp_s, kp_t, matched, credibility, weights, cumulative, min_gap, median_gap)

    # -- the pipeline ----------------------------------------------------------------------------
    def check_options(
        self, iterations: int | None, keypoints: int | None, working_size: int, refine: str | None
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
    ) -> RegistrationResult:
        """Pose ``src_to_tgt`` of ``source [N, 3]`` onto ``target [M, 3]`` (caller's units)."""
        t0 = time.perf_counter()
        timing: dict[str, float] = {}
        src = check_cloud(source, "source")
        tgt = check_cloud(target, "target")
        n_iter, k = self.check_options(iterations, keypoints, working_size, refine)
        R_init, t_init = np.eye(3), np.zeros(3)
        if initial_transform is not None:
            R_init, t_init = check_transform(initial_transform)
        src_moved = src @ R_init.T + t_init  # [N, 3] source in the initial guess's frame

        idx_s = resample_indices(src_moved, working_size)  # [Ns] into the caller's source
        idx_t = resample_indices(tgt, working_size)  # [Nt]
        src_w, tgt_w = src_moved[idx_s], tgt[idx_t]
        norm = Normalization.fit(src_w, tgt_w, self.reference_radius)
        src_n, tgt_n = norm.apply_src(src_w).astype(np.float32), norm.apply_tgt(tgt_w).astype(np.float32)
        warnings = [f"source {w}" if not w.startswith("source") else w for w in degeneracy_warnings(src_w)]
        warnings += [f"target {w}" if not w.startswith("target") else w for w in degeneracy_warnings(tgt_w)]
        t1 = time.perf_counter()
        timing["preprocess"] = 1000 * (t1 - t0)

        net = self.run_network(src_n, tgt_n, n_iter, k, timing)
        t3 = time.perf_counter()
        poses = [
            IterationPose(*self._to_caller(norm, R, t, R_init, t_init))
            for R, t in (net.cumulative if return_iterations else [])
        ]
        R_final, t_final = self._to_caller(norm, net.rotation, net.translation, R_init, t_init)
        scale = norm.scale
        if (refine or "none") == "icp":
            distance = icp_max_distance if icp_max_distance is not None else ICP_DISTANCE * scale
            refined = icp(src[idx_s], tgt_w, R_final, t_final, max_distance=distance, max_iterations=icp_max_iterations)
            R_final, t_final = refined.rotation, refined.translation
            timing["refine"] = 1000 * (time.perf_counter() - t3)
        t4 = time.perf_counter()
        quality = assess(src[idx_s], tgt_w, R_final, t_final, INLIER_DISTANCE * scale)
        warnings = list(dict.fromkeys(warnings + quality.warnings))
        weights = net.weights
        w_sum = weights.sum()
        result = RegistrationResult(
            rotation=R_final,
            translation=t_final,
            source_index=idx_s[net.src_kp].astype(np.int64),
            target_index=idx_t[net.tgt_kp[net.matched]].astype(np.int64),
            credibility=net.credibility.astype(np.float32),
            weight=(weights / (w_sum + 1e-8) if w_sum > 0 else np.full_like(weights, 1 / len(weights))).astype(
                np.float32
            ),
            inlier_ratio=quality.inlier_ratio,
            residual_rms=quality.residual_rms,
            reliable=bool(quality.reliable and not any(_is_degenerate(w) for w in warnings)),
            warnings=warnings,
            iterations=n_iter,
            timing_ms=timing,
            iteration_poses=poses,
        )
        timing["postprocess"] = 1000 * (time.perf_counter() - t4)
        timing["total"] = 1000 * (time.perf_counter() - t0)
        return result

    @staticmethod
    def _to_caller(norm: Normalization, R: np.ndarray, t: np.ndarray, R_init: np.ndarray, t_init: np.ndarray):
        """Pose between normalised clouds -> caller's ``src_to_tgt``, composed after the initial guess."""
        R_c, t_c = norm.unnormalize_pose(R, t)
        return compose(R_c, t_c, R_init, t_init)


def _is_degenerate(warning: str) -> bool:
    return any(word in warning for word in ("identical", "collinear", "empty"))


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
