"""``mfgnet bench``: in-process latency of the ONNX pipeline vs PyTorch eager, per stage and size.

Everything is measured in one run on the same seeded pairs, so ratios are meaningful even on a
noisy machine. Output: JSON (``--json``) and a short table; ``--compare baseline.json`` prints the
change of every figure.
"""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from bench.report_io import machine_info

if TYPE_CHECKING:
    from model.network import MFGNet
    from service.registrar import Registrar

SIZES = (512, 1024, 2048, 4096)  # network working sizes
LARGE_INPUTS = (20_000, 100_000)  # input sizes resampled to the default working size
ITERATIONS = (1, 2, 3, 4, 5, 6)


def percentiles(samples_ms: list[float]) -> dict[str, float]:
    a = np.asarray(samples_ms)
    return {
        "p50": float(np.percentile(a, 50)),
        "p95": float(np.percentile(a, 95)),
        "p99": float(np.percentile(a, 99)),
        "mean": float(a.mean()),
        "n": len(a),
    }


def time_calls(fn: Callable[[], object], repeats: int, warmup: int = 2) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        out.append(1000 * (time.perf_counter() - tic))
    return out


def bench_pipeline(
    registrar: Registrar,
    pairs: dict,
    repeats: int,
    iterations: int | None = None,
    keypoints: int | None = None,
    working_size: int = 768,
) -> dict:
    """Total and per-stage latency of ``Registrar.register`` cycling over the pairs."""
    stages: dict[str, list[float]] = {}
    totals: list[float] = []
    n = len(pairs["source"])
    for i in range(repeats + 2):
        res = registrar.register(
            pairs["source"][i % n],
            pairs["target"][i % n],
            iterations=iterations,
            keypoints=keypoints,
            working_size=working_size,
        )
        if i < 2:
            continue
        totals.append(res.timing_ms["total"])
        for stage, ms in res.timing_ms.items():
            stages.setdefault(stage, []).append(ms)
    return {"total": percentiles(totals), "stages": {k: float(np.median(v)) for k, v in stages.items()}}


def bench_torch(model: MFGNet, pairs: dict, repeats: int, iterations: int | None = None) -> dict:
    import torch

    n = len(pairs["source"])
    state = {"i": 0}

    @torch.no_grad()
    def call():
        i = state["i"] % n
        state["i"] += 1
        model(
            torch.from_numpy(pairs["source"][i : i + 1]),
            torch.from_numpy(pairs["target"][i : i + 1]),
            iterations=iterations,
        )

    return {"total": percentiles(time_calls(call, repeats))}


def run_bench(
    model_name: str,
    checkpoint: str,
    model_dir: Path,
    network: MFGNet,
    repeats: int,
    setting: str,
    seed: int,
    threads: int,
    accuracy_settings: tuple[str, ...] = (),
    accuracy_count: int = 30,
    classical: bool = True,
    http_requests: int = 0,
) -> dict:
    """The report of ``mfgnet bench``: the model in ``model_dir`` (``--model model_name``) against ``network``, the
    eager network of the same weights (``--checkpoint checkpoint``)."""
    import torch

    from model.data import make_test_pairs
    from service.registrar import Registrar

    torch.set_num_threads(threads)
    registrar = Registrar(model_dir, threads=threads)
    model = network
    pairs = make_test_pairs(setting, "test", count=16, seed=seed)
    report: dict = {
        "machine": {**machine_info(threads), "python": platform.python_version()},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "model": model_name,
        "checkpoint": checkpoint,
        "pairs": f"{setting} test pairs, seed {seed}, 768 points per cloud",
    }
    from tqdm import tqdm

    stages = tqdm(total=7 + len(accuracy_settings), desc="bench", unit="stage")
    stages.set_postfix_str("pipeline")
    report["pipeline_768"] = bench_pipeline(registrar, pairs, repeats)
    stages.update()
    stages.set_postfix_str("torch eager")
    report["torch_eager_768"] = bench_torch(model, pairs, repeats)
    report["speedup_vs_torch"] = report["torch_eager_768"]["total"]["p50"] / report["pipeline_768"]["total"]["p50"]
    stages.update()
    stages.set_postfix_str("iterations 1-6")
    report["iterations"] = {
        str(n): bench_pipeline(registrar, pairs, max(5, repeats // 2), iterations=n)["total"] for n in ITERATIONS
    }
    stages.update()
    stages.set_postfix_str("accuracy at 1-6 iterations")
    if accuracy_count:
        report["iteration_accuracy"] = iteration_accuracy(registrar, setting, accuracy_count, seed)
    stages.update()
    stages.set_postfix_str("working sizes")
    sized = {}
    for size in SIZES:
        rng = np.random.default_rng(size)
        resized = {k: [resize_cloud(p, size, rng) for p in pairs[k][:4]] for k in ("source", "target")}
        sized[str(size)] = bench_pipeline(registrar, resized, max(5, repeats // 2), working_size=size)["total"]
    report["working_size"] = sized
    stages.update()
    stages.set_postfix_str("large inputs")
    rng = np.random.default_rng(0)
    inputs = {
        str(n): (resize_cloud(pairs["source"][0], n, rng), resize_cloud(pairs["target"][0], n, rng))
        for n in LARGE_INPUTS
    }
    report["input_size_working_768"] = {
        n: bench_pipeline(registrar, {"source": [s], "target": [t]}, 5)["total"] for n, (s, t) in inputs.items()
    }
    stages.update()
    stages.set_postfix_str("HTTP")
    if http_requests:
        from bench.http_latency import bench_http

        report["http"] = bench_http(pairs, http_requests, inputs, threads)
    stages.update()
    report["accuracy"] = []
    for s in accuracy_settings if accuracy_count else ():
        stages.set_postfix_str(f"side by side: {s}")
        report["accuracy"].append(compare_methods(registrar, model, s, accuracy_count, seed, classical))
        stages.update()
    stages.close()
    return report


def iteration_accuracy(registrar: Registrar, setting: str, count: int, seed: int) -> dict:
    """The paper's ablation: accuracy of the pipeline (no refinement) at 1-6 iterations on the same seeded pairs."""
    from bench.baselines import run_method
    from model.data import make_test_pairs
    from model.metrics import registration_metrics

    pairs = make_test_pairs(setting, "test", count=count, seed=seed)

    def with_iterations(n: int):
        def method(src: np.ndarray, tgt: np.ndarray):
            res = registrar.register(src, tgt, iterations=n)
            return res.rotation, res.translation

        return method

    out = {"setting": setting, "count": count, "seed": seed}
    for n in ITERATIONS:
        R, t, seconds = run_method(with_iterations(n), pairs)
        out[str(n)] = registration_metrics(R, t, pairs["rotation"], pairs["translation"], seconds)
    return out


def resize_cloud(points: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """``size`` points: a random subset, or the cloud plus jittered copies of its points."""
    if size <= len(points):
        return points[rng.choice(len(points), size, replace=False)]
    extra = points[rng.integers(0, len(points), size - len(points))] + rng.normal(0, 0.005, (size - len(points), 3))
    return np.concatenate([points, extra.astype(points.dtype)])


def compare_methods(registrar: Registrar, model: MFGNet, setting: str, count: int, seed: int,
                    classical: bool = True) -> dict:
    """Accuracy (the paper's metrics) and ms per pair of every method on the same seeded pairs."""
    import torch

    from model.data import make_test_pairs
    from model.metrics import registration_metrics

    pairs = make_test_pairs(setting, "test", count=count, seed=seed)

    def pipeline(refine: str, rotation_search: bool | str = False):
        def method(src: np.ndarray, tgt: np.ndarray):
            res = registrar.register(src, tgt, refine=refine, rotation_search=rotation_search)
            return res.rotation, res.translation

        return method

    @torch.no_grad()
    def eager(src: np.ndarray, tgt: np.ndarray):
        out = model(torch.from_numpy(src[None]), torch.from_numpy(tgt[None]))
        return out.rotation[0].double().numpy(), out.translation[0].double().numpy()

    methods = {
        "torch_eager": eager,
        "onnx_pipeline": pipeline("none"),
        "onnx_pipeline_icp": pipeline("icp"),
        "onnx_pipeline_icp_plane": pipeline("icp-plane"),
        "onnx_auto_search_icp_plane": pipeline("icp-plane", rotation_search="auto"),
        "onnx_search_icp_plane": pipeline("icp-plane", rotation_search=True),
    }
    if classical:
        from bench.baselines import fgr, fpfh_ransac_icp

        methods["fpfh_ransac_icp"] = fpfh_ransac_icp
        methods["fgr"] = fgr
    from bench.baselines import run_method

    results = {}
    for name, method in methods.items():
        R, t, seconds = run_method(method, pairs)
        results[name] = registration_metrics(R, t, pairs["rotation"], pairs["translation"], seconds)
    return {"setting": setting, "count": count, "seed": seed, "methods": results}


def flatten(d: dict, prefix: str = "") -> dict[str, float]:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[key] = float(v)
    return out


def same_network(folder: Path, path: Path, model: str, checkpoint: str) -> None:
    """A usage error where the model ``folder``'s manifest records the checkpoint it was exported from and ``path`` is
    another: the eager figures would time another network than the ONNX ones."""
    from model.checkpoint import file_sha256
    from model.cli_inputs import fail
    from service.manifest import load_manifest

    raw = load_manifest(folder).raw
    exported_from = raw.get("source_checkpoint_sha256")
    if exported_from and exported_from != file_sha256(path):
        fail(f"--checkpoint {checkpoint}: not the checkpoint --model {model} was exported from ({raw.get('source')}, "
             "by its manifest); give --checkpoint that file, so that the eager and ONNX figures time one network")


def bench(
    model: Annotated[str, typer.Option(help="bundled model name or model folder")] = "clean",
    checkpoint: Annotated[str, typer.Option(help="checkpoint with the same weights (torch eager)")] = "clean",
    repeats: Annotated[int, typer.Option(min=1, help="timed calls per figure")] = 30,
    setting: Annotated[str, typer.Option(help="setting of the latency pairs")] = "clean",
    seed: Annotated[int, typer.Option(min=0, help="seed of the test pairs")] = 0,
    threads: Annotated[int, typer.Option(min=1, help="ONNX Runtime and torch threads")] = 2,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the report here")] = None,
    compare: Annotated[Path | None, typer.Option(help="baseline report: print the change per figure")] = None,
    accuracy_setting: Annotated[list[str] | None, typer.Option(
        help="settings for the side-by-side accuracy (repeat the option; none: no accuracy stages)")] = None,
    accuracy_count: Annotated[
        int, typer.Option(min=0, help="pairs per accuracy figure, with --accuracy-setting (0: skip the accuracy "
                                      "stages)")
    ] = 30,
    classical: Annotated[bool, typer.Option(help="include Open3D FPFH+RANSAC+ICP and FGR in the side-by-side "
                                                 "accuracy (--accuracy-setting)")] = True,
    http_requests: Annotated[
        int, typer.Option(min=0, help="requests per concurrency level over HTTP (0: skip)")
    ] = 100,
) -> None:
    """Latency of the ONNX pipeline (per stage, sizes, iterations) against PyTorch eager on the --setting pairs, and,
    with --accuracy-setting, accuracy and time side by side with Open3D FPFH + RANSAC + ICP and FGR on the same seeded
    pairs."""
    from model.cli_inputs import checkpoint_model, model_dir, output_file, require_shapes
    from model.data import DATA_ENV

    if json_out:
        output_file(json_out, "--json", create_folders=True)
    baseline = bench_report(compare, "--compare") if compare else None
    folder = model_dir(model)
    path, _, network = checkpoint_model(checkpoint)
    same_network(folder, path, model, checkpoint)
    for name in (setting, *(accuracy_setting or () if accuracy_count else ())):
        require_shapes("test", name, None, hint=f"set ${DATA_ENV}")
    if classical and accuracy_setting and accuracy_count:
        from bench.baselines import open3d_missing

        if (hint := open3d_missing()) is not None:  # before the latency stages, not after them
            raise typer.BadParameter(f"{hint}; or --no-classical", param_hint="--classical")
    report = run_bench(
        model,
        checkpoint,
        folder,
        network,
        repeats,
        setting,
        seed,
        threads,
        tuple(accuracy_setting or ()),
        accuracy_count,
        classical,
        http_requests,
    )
    text = json.dumps(report, indent=2)
    if json_out:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(text + "\n")
    typer.echo(text)
    if baseline is not None:
        base, now = flatten(baseline), flatten(report)
        for key in sorted(set(base) & set(now)):
            if base[key]:
                typer.echo(
                    f"{key:45s} {base[key]:10.3f} -> {now[key]:10.3f} ({100 * (now[key] / base[key] - 1):+.1f}%)"
                )


def bench_report(path: Path, option: str) -> dict:
    """The report of an earlier ``mfgnet bench --json`` at ``path``, or a usage error."""
    from model.cli_inputs import fail, json_file

    report = json_file(path, option)
    if not isinstance(report, dict) or "pipeline_768" not in report:
        what = f"a JSON {type(report).__name__}" if not isinstance(report, dict) else "no 'pipeline_768'"
        fail(f"{option} {path}: not an mfgnet bench report ({what})")
    return report
