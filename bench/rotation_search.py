"""Rotation search: success rate and cost of ``Registrar.register(rotation_search=True)``.

Run as ``python -m bench.rotation_search --json rotation_search.json`` (figures of
``docs/ROTATION_SEARCH.md``). On seeded ``dense`` / ``resampled`` pairs with ``--max-angle`` 45, 90,
180 it registers every pair four ways, all through the real ONNX pipeline (``refine="icp"``):

* ``plain``: no search;
* ``search``: ``rotation_search=True`` (the shipped method: every hypothesis gets a short wide-basin
  ICP, the best is refined);
* ``search_net_rank``: ``rotation_search=True, refine="none"`` (hypotheses ranked on the raw
  network poses), then the pipeline's own ICP on the winner, i.e. "select, then refine";
* ``starts_icp``: no network: the same short ICP from each of the 24 start rotations (centroids
  aligned), ranked and refined the same way (how much the network adds).

Success = rotation error < 5 degrees and translation error < 0.05 (the ``recall_r5_t005`` of
``model.metrics``). ``as_good_as_truth`` = the final pose's inlier ratio is at least 98% of the
ground-truth pose's on the same working clouds: wrong by rotation error, but an equally good fit
(symmetric shapes: the 180-degree flips of airplanes, bathtubs and benches).
"""

from __future__ import annotations

import json
import time
from datetime import date
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from bench.report_io import machine_info

if TYPE_CHECKING:
    from service.normalization import Normalization
    from service.registrar import Registrar

METHODS = ("plain", "search", "search_net_rank", "starts_icp")


def pose_errors(R: np.ndarray, t: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray) -> tuple[float, float]:
    from model.metrics import rotation_angle_deg

    return float(rotation_angle_deg(R[None], R_gt[None])[0]), float(np.linalg.norm(t - t_gt))


def working_clouds(registrar: Registrar, src: np.ndarray, tgt: np.ndarray,
                   working_size: int = 768) -> tuple[np.ndarray, np.ndarray, Normalization]:
    """The registrar's working clouds (caller's units) and their normalisation, as ``register`` builds them."""
    from service.normalization import Normalization
    from service.sampling import resample_indices

    src_w, tgt_w = src[resample_indices(src, working_size, True)], tgt[resample_indices(tgt, working_size, True)]
    return src_w, tgt_w, Normalization.fit(src_w, tgt_w, registrar.reference_radius)


def starts_icp(registrar: Registrar, src_w: np.ndarray, tgt_w: np.ndarray,
               norm: Normalization) -> tuple[np.ndarray, np.ndarray]:
    """The search without the network: short ICP from every start rotation, rank, refine (caller's units)."""
    from service import registrar as reg
    from service import rotation_search as search
    from service.icp import icp

    src_n, tgt_n = norm.apply_src(src_w), norm.apply_tgt(tgt_w)
    starts = search.search_rotations_for(24)
    short = [icp(src_n, tgt_n, R, np.zeros(3), max_distance=search.SEARCH_ICP_DISTANCE,
                 max_iterations=search.SEARCH_ICP_ITERATIONS, reciprocal=False) for R in starts]
    R_h, t_h = np.stack([s.rotation for s in short]), np.stack([s.translation for s in short])
    best = search.rank_hypotheses(src_n, tgt_n, R_h, t_h, reg.INLIER_DISTANCE)[0][0]
    R, t = norm.unnormalize_pose(R_h[best], t_h[best])
    refined = icp(src_w, tgt_w, R, t, max_distance=reg.ICP_DISTANCE * norm.scale)
    return refined.rotation, refined.translation


def evaluate_pair(registrar: Registrar, src: np.ndarray, tgt: np.ndarray, R_gt: np.ndarray,
                  t_gt: np.ndarray) -> dict[str, dict[str, float]]:
    from service import registrar as reg
    from service.icp import icp
    from service.quality import assess

    src, tgt = src.astype(np.float64), tgt.astype(np.float64)
    src_w, tgt_w, norm = working_clouds(registrar, src, tgt)
    inlier = reg.INLIER_DISTANCE * norm.scale
    truth = assess(src_w, tgt_w, R_gt, t_gt, inlier).inlier_ratio
    poses: dict[str, tuple[np.ndarray, np.ndarray, float]] = {}
    for name, kwargs in (("plain", {}), ("search", {"rotation_search": True})):
        res = registrar.register(src, tgt, refine="icp", **kwargs)
        poses[name] = (res.rotation, res.translation, res.timing_ms["total"])
    tic = time.perf_counter()
    res = registrar.register(src, tgt, refine="none", rotation_search=True)
    refined = icp(src_w, tgt_w, res.rotation, res.translation, max_distance=reg.ICP_DISTANCE * norm.scale)
    poses["search_net_rank"] = (refined.rotation, refined.translation, 1000 * (time.perf_counter() - tic))
    tic = time.perf_counter()
    poses["starts_icp"] = (*starts_icp(registrar, src_w, tgt_w, norm), 1000 * (time.perf_counter() - tic))
    out = {}
    for name, (R, t, ms) in poses.items():
        r_err, t_err = pose_errors(R, t, R_gt, t_gt)
        fit = assess(src_w, tgt_w, R, t, inlier).inlier_ratio
        out[name] = {"rot_err": r_err, "trans_err": t_err, "inlier_ratio": fit, "truth_inlier_ratio": truth,
                     "ms": ms}
    return out


def summarise(records: list[dict[str, dict[str, float]]]) -> dict[str, dict[str, float]]:
    summary = {}
    for name in METHODS:
        r = np.array([rec[name]["rot_err"] for rec in records])
        t = np.array([rec[name]["trans_err"] for rec in records])
        fit = np.array([rec[name]["inlier_ratio"] >= 0.98 * rec[name]["truth_inlier_ratio"] for rec in records])
        flip = (r > 150) & fit
        summary[name] = {"success_r5_t005": float(np.mean((r < 5) & (t < 0.05))), "rot_err_median": float(np.median(r)),
                         "as_good_as_truth": float(fit.mean()), "flips_as_good_as_truth": float(flip.mean())}
    return summary


def time_registrations(registrar: Registrar, pairs: dict, repeats: int) -> dict[str, dict[str, float]]:
    """Median ``timing_ms`` stages of ``repeats`` registrations per configuration, after one warm-up round.

    Configurations are interleaved (one call of each per round, same pair), so a machine whose load
    drifts during the run weighs on all of them alike.
    """
    configs = {
        "plain_none": {"refine": "none"},
        "plain_icp": {"refine": "icp"},
        "search24_none": {"refine": "none", "rotation_search": True},
        "search24_icp": {"refine": "icp", "rotation_search": True},
        "search60_icp": {"refine": "icp", "rotation_search": True, "search_rotations": 60},
    }
    n = len(pairs["source"])
    stages: dict[str, dict[str, list[float]]] = {name: {} for name in configs}
    for i in range(repeats + 1):
        for name, kwargs in configs.items():
            res = registrar.register(pairs["source"][i % n], pairs["target"][i % n], **kwargs)
            for stage, ms in res.timing_ms.items():
                if i > 0:
                    stages[name].setdefault(stage, []).append(ms)
    return {name: {**{k: float(np.median(v)) for k, v in s.items()}, "runs": repeats} for name, s in stages.items()}


def search_bench(
    json_out: Annotated[Path, typer.Option("--json", help="write the figures here")] = Path("rotation_search.json"),
    model: Annotated[str, typer.Option(help="bundled model name or model directory")] = "clean",
    count: Annotated[int, typer.Option(min=1, help="pairs per setting and angle")] = 30,
    seed: Annotated[int, typer.Option(min=0, help="seed of the test pairs")] = 0,
    settings: Annotated[list[str] | None, typer.Option("--setting")] = None,
    angles: Annotated[list[float] | None, typer.Option("--max-angle")] = None,
    repeats: Annotated[int, typer.Option(min=1, help="timed registrations per configuration")] = 12,
    threads: Annotated[int, typer.Option(min=1, help="ONNX Runtime threads for the timed runs")] = 2,
    success_threads: Annotated[int, typer.Option(min=1, help="threads for the success-rate runs")] = 1,
    skip_success: bool = False,
    skip_cost: bool = False,
) -> None:
    """Success rate (pairs per setting and angle) and cost of the rotation search."""
    from tqdm import tqdm

    from model.cli_inputs import model_dir, output_file, require_shapes
    from model.data import DATA_ENV, make_test_pairs, protocol_for
    from service.manifest import load_manifest, model_folder
    from service.registrar import Registrar

    settings = settings or ["dense", "resampled"]
    output_file(json_out, "--json")  # before any work: the report is first written after the cost stage
    model_dir(model)
    for setting in dict.fromkeys(["dense", *settings]):  # the cost stage's pairs, then each setting's
        require_shapes("test", setting, None, hint=f"set ${DATA_ENV}")
    angles = angles or [45.0, 90.0, 180.0]
    model_dir = model_folder(model)
    registrar = Registrar(model_dir, threads=threads)
    manifest = load_manifest(model_dir)
    report = {
        "date": date.today().isoformat(),
        "machine": machine_info(threads),
        "model": {"dir": str(model_dir), "name": manifest.name, "created": manifest.raw.get("created"),
                  "source": manifest.raw.get("source"),
                  "source_checkpoint_sha256": manifest.raw.get("source_checkpoint_sha256"),
                  "graph_sha256": {k: v.get("sha256") for k, v in manifest.raw.get("graphs", {}).items()}},
        "command": "python -m bench.rotation_search " + " ".join(
            [f"--count {count}", f"--seed {seed}", f"--repeats {repeats}", f"--threads {threads}",
             f"--success-threads {success_threads}"]),
        "cost_ms": {} if skip_cost else time_registrations(registrar, make_test_pairs("dense", count=6, seed=seed),
                                                             repeats),
        "success": {},
    }
    print(json.dumps(report["cost_ms"], indent=1))
    json_out.write_text(json.dumps(report, indent=1) + "\n")
    registrar = Registrar(model_dir, threads=success_threads)
    if not skip_success:
        for setting in settings:
            for angle in angles:
                protocol = protocol_for(setting, max_angle=angle)
                pairs = make_test_pairs(setting, count=count, seed=seed, protocol=protocol)
                records = [
                    evaluate_pair(registrar, *(pairs[k][i] for k in ("source", "target", "rotation", "translation")))
                    for i in tqdm(range(len(pairs["source"])), desc=f"{setting} {angle:g}", mininterval=10)
                ]
                key = f"{setting}_{angle:g}"
                report["success"][key] = {"pairs": len(records), **summarise(records)}
                report.setdefault("records", {})[key] = records
                print(key, json.dumps(report["success"][key]))
                json_out.write_text(json.dumps(report, indent=1) + "\n")
    json_out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    typer.run(search_bench)
