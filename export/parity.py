"""Parity of the exported graphs with PyTorch, through the runtime's own pipeline (``Registrar``)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from export import MIN_COMPARED
from model.metrics import rotation_angle_deg
from model.network import MFGNet, RegistrationOutput, knn_indices
from service.network_loop import NetworkOutput
from service.registrar import Registrar, embedding_distance

GRAPH_TOL = 1e-4  # per graph output: absolute up to a largest |value| of 1, relative to that largest |value| above
ROTATION_TOL_DEG = 1e-3
TRANSLATION_TOL = 1e-5
TIE_GAP = 1e-5  # pairs whose best two matching scores are closer than this may flip argmax
SELECTION_GAP = GRAPH_TOL  # significance / credibility near-ties within the graph tolerance
# below this embedding spread (median keypoint embedding distance / median embedding size) the embeddings are nearly
# identical, as an untrained network's are: the README's 3-batch smoke run gives 6e-5, the bundled models 0.49-0.72
EMBEDDING_SPREAD_MIN = 1e-2


class ParityError(AssertionError):
    """The exported graphs do not reproduce the PyTorch model; ``nearly_identical_embeddings`` where the keypoint
    embeddings hardly differ (an untrained network's signature, :data:`EMBEDDING_SPREAD_MIN`)."""

    def __init__(self, message: str, nearly_identical_embeddings: bool = False):
        super().__init__(message)
        self.nearly_identical_embeddings = nearly_identical_embeddings


@dataclass
class ParityReport:
    pairs: int
    compared: int
    excluded_ties: int
    keypoint_boundary_ties: int  # pairs where the K-th / (K+1)-th significance scores nearly tie
    knn_ties: int  # pairs whose runtime k-NN graph differs from the model's (distance ties; excluded)
    max_encoder_diff: float  # graph differences as compared with GRAPH_TOL: max |onnx - torch| / max(1, max |torch|)
    max_matcher_diff: float
    max_rotation_diff_deg: float
    max_translation_diff: float
    embedding_spread: float | None = None  # median over pairs of :func:`embedding_spread` of the keypoints

    def to_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def check_parity(
    model: MFGNet,
    registrar: Registrar,
    pairs: dict[str, np.ndarray],
    iterations: int | None = None,
    keypoints: int | None = None,
    min_compared: int = MIN_COMPARED,
) -> ParityReport:
    """Compare per-graph outputs and final poses of ``registrar`` and ``model`` on ``pairs``.

    Raises ``ParityError`` when a tolerance is exceeded or fewer than ``min_compared`` pairs are
    comparable (pairs with near-tied matching scores are excluded and counted). The outputs of every graph (the
    encoder and each matcher) are compared on every pair, ties or not.
    """
    model = model.eval()
    n_iter = iterations or model.cfg.iterations
    K = keypoints or model.cfg.keypoints
    n_matchers = max(len(model.matchers), len(registrar.matchers))  # each index past the last reuses the last
    enc_diff = match_diff = rot_diff = trans_diff = 0.0
    compared = excluded = boundary = knn_ties = 0
    spreads = []
    for src, tgt in zip(pairs["source"], pairs["target"], strict=True):
        src_t, tgt_t = _tensor(src[None]), _tensor(tgt[None])
        nb_s, nb_t = registrar.neighbours(src[None]), registrar.neighbours(tgt[None])
        # the runtime's KD-tree and the model's float32 distances can only disagree at distance ties
        same_graphs = all(
            _same_graph(nb, knn_indices(cloud, model.cfg.knn).numpy()) for nb, cloud in ((nb_s, src_t), (nb_t, tgt_t))
        )
        knn_ties += not same_graphs
        emb_ref, score_ref = model.embed(src_t, torch.from_numpy(nb_s))  # per graph: the same inputs
        emb, score = registrar.embed(src[None], nb_s)
        enc_diff = max(enc_diff, _graph_diff(emb, emb_ref), _graph_diff(score, score_ref))
        e_s, (e_t, score_t) = emb, registrar.embed(tgt[None], nb_t)
        out = registrar.run_network(src, tgt, n_iter, K)
        ref = model(src_t, tgt_t, iterations=n_iter, keypoints=K)
        if not _same_keypoints(ref, out):
            # Top-K is the same sort on both sides; it can only differ where scores nearly tie.
            if min(_boundary_gap(score[0], K), _boundary_gap(score_t[0], K)) >= SELECTION_GAP:
                raise ParityError(f"keypoint selection differs without a near-tie (pair {compared + excluded})")
            boundary += 1
            ref = model(
                src_t,
                tgt_t,
                iterations=n_iter,
                keypoints=K,
                src_idx=_tensor(out.src_kp[None]),
                tgt_idx=_tensor(out.tgt_kp[None]),
            )
        # every matcher graph (one per weight set) on the same inputs, those of the reference's first iteration:
        # a later graph is otherwise seen only through the final pose, on the comparable pairs
        ps, pt = src[out.src_kp][None], tgt[out.tgt_kp][None]  # [1, K, 3], [1, K, 3]
        es, et = e_s[:, out.src_kp], e_t[:, out.tgt_kp]  # [1, K, D], [1, K, D]
        spreads.append(embedding_spread(es[0], et[0]))
        ref_inputs = [_tensor(a) for a in (ps, pt, es, et)]
        for i in range(n_matchers):
            scores, logit = registrar.match(i, ps, pt, es, et)  # [1, K, K], [1, K]
            s_ref, l_ref = model.matcher(i)(*ref_inputs)
            match_diff = max(match_diff, _graph_diff(scores, s_ref), _graph_diff(logit, l_ref))
        if out.min_top2_gap < TIE_GAP or out.min_median_gap < SELECTION_GAP or not same_graphs:
            excluded += 1
            continue
        compared += 1
        rot_diff = max(rot_diff, float(rotation_angle_deg(out.rotation[None], ref.rotation.double().numpy())[0]))
        trans_diff = max(trans_diff, float(np.abs(out.translation - ref.translation[0].double().numpy()).max()))
    spread = float(np.median(spreads)) if spreads else None
    report = ParityReport(
        len(pairs["source"]), compared, excluded, boundary, knn_ties, enc_diff, match_diff, rot_diff, trans_diff, spread
    )
    problems = []
    collapsed = spread is not None and spread < EMBEDDING_SPREAD_MIN
    if enc_diff > GRAPH_TOL:
        problems.append(f"encoder differs by {enc_diff:.2e} > {GRAPH_TOL}")
    if match_diff > GRAPH_TOL:
        problems.append(f"matcher differs by {match_diff:.2e} > {GRAPH_TOL}")
    if rot_diff > ROTATION_TOL_DEG:
        problems.append(f"rotation differs by {rot_diff:.2e} deg > {ROTATION_TOL_DEG}")
    if trans_diff > TRANSLATION_TOL:
        problems.append(f"translation differs by {trans_diff:.2e} > {TRANSLATION_TOL}")
    if compared < min_compared:
        more = "" if collapsed else (" (more --parity-pairs give more comparable ones where the test split holds the "
                                     "shapes; a split of fewer shapes: a lower --min-comparable)")
        problems.append(f"only {compared} comparable pairs (< {min_compared}); {excluded} of {len(pairs['source'])} "
                        f"excluded as ties{more}")
    if problems:
        cause = _collapsed_cause(spread, match_diff > GRAPH_TOL, compared < min_compared) if collapsed else ""
        raise ParityError("ONNX parity failed: " + "; ".join(problems) + f" ({report.to_dict()})" + cause, collapsed)
    return report


def embedding_spread(emb_a: np.ndarray, emb_b: np.ndarray) -> float:
    """How far apart the keypoint embeddings ``emb_a [K, D]``, ``emb_b [L, D]`` of a pair lie, relative to their
    size: median ``||a_i - b_j||`` over the ``K x L`` pairs / median ``||e||`` over all ``K + L`` embeddings."""
    dist = embedding_distance(emb_a[None], emb_b[None])  # [1, K, L]
    size = np.median(np.linalg.norm(np.concatenate([emb_a, emb_b]).astype(np.float64), axis=-1))  # no overflow
    return float(np.median(dist) / max(float(size), np.finfo(np.float64).tiny))


def _collapsed_cause(spread: float, matcher_differs: bool, too_few_compared: bool) -> str:
    """The likely cause of a failure whose keypoint embeddings are nearly identical (``spread``)."""
    effects = []
    if matcher_differs:
        effects.append("the export's pair layer, inv * pa - inv * pb with inv = 1 / ||a - b|| (docs/decisions/"
                       "0005-export-only-graph-rewrites.md), then cancels to float32 rounding")
    if too_few_compared:
        effects.append("its matching scores nearly tie, so the pairs are excluded as ties")
    return (f". Likely cause: the keypoint embeddings are nearly identical (median distance {spread:.1e} of their "
            f"size, < {EMBEDDING_SPREAD_MIN}), as an untrained or barely trained network's are"
            + (": " + "; ".join(effects) if effects else ""))


def _tensor(array: np.ndarray) -> torch.Tensor:
    """A tensor copy of ``array``, which may be a read-only view (the runtime's target keypoints of a single pair are
    a broadcast view; the caller's pairs may be memory-mapped): ``torch.from_numpy`` of one warns."""
    return torch.tensor(array)


def _graph_diff(out: np.ndarray, ref: torch.Tensor) -> float:
    """Largest difference of a graph output from the eager model's, relative to the output's largest magnitude where
    that is above 1: float32 sums round relative to the size of their terms (a matcher's credibility logits reach 11,
    with rounding differences of 1e-4 on values near 1; its scores reach the clamp at 20)."""
    ref_np = ref.numpy()
    diff = float(np.abs(out - ref_np).max() / max(1.0, float(np.abs(ref_np).max())))
    return diff if math.isfinite(diff) else math.inf  # NaN would vanish in max(); a NaN output is no match


def _same_graph(a: np.ndarray, b: np.ndarray) -> bool:
    """Two k-NN graphs ``[B, N, k]`` with the same neighbour set per point (order is irrelevant)."""
    return bool(np.array_equal(np.sort(a, axis=-1), np.sort(b, axis=-1)))


def _same_keypoints(ref: RegistrationOutput, out: NetworkOutput) -> bool:
    return set(ref.src_idx[0].tolist()) == set(out.src_kp.tolist()) and set(ref.tgt_idx[0].tolist()) == set(
        out.tgt_kp.tolist()
    )


def _boundary_gap(scores: np.ndarray, k: int) -> float:
    """Gap between the K-th and (K+1)-th highest significance scores of one cloud."""
    if len(scores) <= k:
        return np.inf
    top = np.sort(scores)[::-1]
    return float(top[k - 1] - top[k])
