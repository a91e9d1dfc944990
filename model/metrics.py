"""The paper's registration metrics (RMSE / MAE of Euler angles and translation) plus isotropic
errors and recall, pooled over all pairs. Pure numpy + scipy."""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
from scipy.spatial.transform import Rotation

RECALL_THRESHOLDS = {"recall_r1_t001": (1.0, 0.01), "recall_r5_t005": (5.0, 0.05)}


def euler_zyx_deg(R: np.ndarray) -> np.ndarray:
    """``[M, 3, 3]`` rotations -> ``[M, 3]`` Euler angles, scipy ``as_euler("zyx", degrees=True)``."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_euler("zyx", degrees=True)


def rotation_angle_deg(R_pred: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Isotropic rotation error ``angle(R_pred^T R_gt)`` in degrees, ``[M]``.

    Uses ``||R_pred - R_gt||_F = 2 sqrt(2) sin(angle / 2)``, which stays accurate for tiny angles
    (``arccos`` of the trace loses ~0.03 deg to float32 rounding).
    """
    diff = np.asarray(R_pred, np.float64) - np.asarray(R_gt, np.float64)  # [M, 3, 3]
    chord = np.sqrt((diff**2).sum(axis=(1, 2))) / (2.0 * np.sqrt(2.0))
    return np.degrees(2.0 * np.arcsin(np.clip(chord, 0.0, 1.0)))


def isotropic_errors(R_pred: np.ndarray, t_pred: np.ndarray, R_gt: np.ndarray,
                     t_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair, the rotation error in degrees ``[M]`` (:func:`rotation_angle_deg`) and the translation error."""
    iso_t = np.linalg.norm(np.asarray(t_pred, np.float64) - np.asarray(t_gt, np.float64), axis=1)  # [M]
    return rotation_angle_deg(R_pred, R_gt), iso_t


def recall_hits(iso_r: np.ndarray, iso_t: np.ndarray) -> dict[str, np.ndarray]:
    """Per pair, whether it counts for each recall: ``{key: bool [M]}`` from isotropic errors ``[M]``."""
    return {key: (iso_r < max_r) & (iso_t < max_t) for key, (max_r, max_t) in RECALL_THRESHOLDS.items()}


def registration_metrics(R_pred: np.ndarray, t_pred: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray,
                         seconds: float | None = None) -> dict[str, float]:
    """Metrics over ``M`` pairs: ``R [M, 3, 3]``, ``t [M, 3]``.

    ``rmse_r`` / ``mae_r`` pool the differences of the ``zyx`` Euler angles over all pairs and the three
    angles, and ``rmse_t`` / ``mae_t`` those of the translation components, as the authors' test code does.
    Euler differences are wrapped into ``[-180, 180)`` degrees, which the authors' code does not do: the
    two agree wherever every predicted angle is within 180 degrees of the true one (every pair of the
    paper's 45-degree protocol unless the prediction is far off); beyond, only the wrapped one is right.
    A predicted pose holding NaN or inf counts as infinitely off (its errors ``inf``, never within a recall
    threshold) and ``non_finite`` counts them, instead of scipy's error ending the evaluation or the training.
    """
    R_pred, R_gt = np.asarray(R_pred, np.float64), np.asarray(R_gt, np.float64)
    t_pred, t_gt = np.asarray(t_pred, np.float64), np.asarray(t_gt, np.float64)
    finite = np.isfinite(R_pred).all(axis=(1, 2)) & np.isfinite(t_pred).all(axis=1)  # [M]
    d_euler = np.full(t_pred.shape, np.inf)  # [M, 3]; a pose with NaN or inf (a diverged network) is infinitely off
    d_euler[finite] = euler_zyx_deg(R_pred[finite]) - euler_zyx_deg(R_gt[finite])  # scipy refuses NaN matrices
    d_euler[finite] = (d_euler[finite] + 180.0) % 360.0 - 180.0
    d_t = np.where(finite[:, None], t_pred - t_gt, np.inf)  # [M, 3]
    iso_r = np.where(finite, rotation_angle_deg(R_pred, R_gt), np.inf)  # [M]
    iso_t = np.linalg.norm(d_t, axis=1)  # [M]
    out = {
        "n": len(R_pred),
        "rmse_r": float(np.sqrt(np.mean(d_euler**2))),
        "mae_r": float(np.mean(np.abs(d_euler))),
        "rmse_t": float(np.sqrt(np.mean(d_t**2))),
        "mae_t": float(np.mean(np.abs(d_t))),
        "iso_r_mean": float(iso_r.mean()),
        "iso_r_median": float(np.median(iso_r)),
        "iso_t_mean": float(iso_t.mean()),
        "iso_t_median": float(np.median(iso_t)),
    }
    out.update({key: float(hits.mean()) for key, hits in recall_hits(iso_r, iso_t).items()})
    if not finite.all():
        out["non_finite"] = int((~finite).sum())  # poses holding NaN or inf, counted infinitely off
    if seconds is not None:
        out["ms_per_pair"] = 1000.0 * seconds / max(len(R_pred), 1)
    return out


def reliability_metrics(R_pred: np.ndarray, t_pred: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray,
                        reliable: np.ndarray) -> dict[str, float]:
    """How well the runtime's ``quality.reliable`` flags ``reliable [M]`` separate right from wrong poses (right =
    within (5 deg, 5 cm), as ``recall_r5_t005``): the share flagged reliable, the share flagged reliable but
    wrong (the errors a caller trusting the flag would take) and the share right but flagged unreliable."""
    iso_r, iso_t = isotropic_errors(R_pred, t_pred, R_gt, t_gt)  # [M], [M]
    right = recall_hits(iso_r, iso_t)["recall_r5_t005"]  # [M]
    reliable = np.asarray(reliable, dtype=bool)
    return {
        "reliable_share": float(reliable.mean()),
        "reliable_wrong_share": float((reliable & ~right).mean()),
        "unreliable_right_share": float((~reliable & right).mean()),
    }


def warnings_by_outcome(R_pred: np.ndarray, t_pred: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray,
                        reliable: np.ndarray, warnings: list[tuple[str, ...]]) -> dict[str, dict[str, int]]:
    """What the runtime said where ``quality.reliable`` misled: for the right results flagged unreliable and the
    wrong ones called reliable (right as in :func:`reliability_metrics`), how many carried each set of warning kinds
    (``warnings [M]``: per pair its kinds; a set is its kinds joined by " + ", "none" for no warning)."""
    iso_r, iso_t = isotropic_errors(R_pred, t_pred, R_gt, t_gt)  # [M], [M]
    right = recall_hits(iso_r, iso_t)["recall_r5_t005"]  # [M]
    reliable = np.asarray(reliable, dtype=bool)
    out: dict[str, dict[str, int]] = {}
    for outcome, mask in (("right_unreliable", right & ~reliable), ("wrong_reliable", ~right & reliable)):
        counts = Counter(" + ".join(warnings[i]) or "none" for i in np.flatnonzero(mask))
        out[outcome] = dict(sorted(counts.items(), key=lambda item: (-item[1], item[0])))
    return out


def recall_by_label(R_pred: np.ndarray, t_pred: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, labels: np.ndarray,
                    names: list[str] | None = None) -> dict[str, dict]:
    """Recall per class: ``{"<label>": {"n", "recall_r1_t001", "recall_r5_t005"[, "name"]}}`` over the pairs
    ``R [M, 3, 3]``, ``t [M, 3]`` with ``labels [M]`` (``names[label]`` when given): which classes fail."""
    iso_r, iso_t = isotropic_errors(R_pred, t_pred, R_gt, t_gt)  # [M], [M]
    hits = recall_hits(iso_r, iso_t)
    labels = np.asarray(labels)
    out: dict[str, dict] = {}
    for label in np.unique(labels):
        mask = labels == label
        entry: dict = {"n": int(mask.sum())}
        if names is not None and 0 <= int(label) < len(names):
            entry["name"] = names[int(label)]
        entry.update({key: float(h[mask].mean()) for key, h in hits.items()})
        out[str(int(label))] = entry
    return out


def save_per_pair(path: str | os.PathLike, R_pred: np.ndarray, t_pred: np.ndarray, pairs: dict[str, np.ndarray],
                  reliable: np.ndarray | None = None, stability: np.ndarray | None = None) -> None:
    """Each pair's predicted pose ``[M, 3, 3]``, ``[M, 3]`` and its isotropic errors (``rotation_error_deg``,
    ``translation_error``), plus the pairs' ``label`` when they have one and the runtime's ``reliable [M]`` and
    ``stability [M]`` (NaN where none) when given, as an ``.npz`` for failure analysis."""
    out = {
        "rotation": R_pred,
        "translation": t_pred,
        "rotation_error_deg": rotation_angle_deg(R_pred, pairs["rotation"]),
        "translation_error": np.linalg.norm(t_pred - pairs["translation"], axis=-1),
    }
    if "label" in pairs:
        out["label"] = pairs["label"]
    if reliable is not None:
        out["reliable"] = np.asarray(reliable, dtype=bool)
    if stability is not None:
        out["stability"] = np.asarray(stability, dtype=np.float64)
    np.savez(path, **out)
