"""Where a bundled model's graphs spend their time, per ONNX Runtime op type, and their GEMM floor.

``python -m bench.graph_ops --pairs dense.npz [--model general|FOLDER] [--repeats 30] [--json out.json]``

Registers the first pair once with ``Registrar.register`` to capture the encoder's and each matcher's real
inputs, then runs each graph ``repeats`` times on them in a fresh session with ONNX Runtime's profiler on
(the registrar's thread count and options otherwise). For each graph it reports the time per call and per
op type, and for the matrix products (``MatMul``, ``Gemm`` and their fused forms) the multiply-adds from
the profiled shapes and the rate reached, for all of them and for the wide ones (inner size and output
width both at least ``WIDE``: the compute-bound edge and hidden layers; narrow ones such as
``[K, L, 3] x [3, C]`` or a score head's ``[K * L, 32] x [32, 1]`` move memory more than they compute).
``registration`` adds each figure over one default registration (the encoder as often as it ran: once for both
clouds of one size, once per cloud where their sizes differ; each iteration's matcher once): no
rewrite of the element-wise work takes a float32 registration on this machine below its
``wide_products_ms``; only fewer multiply-adds (a smaller network) would.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnxruntime as ort

from bench.report_io import checked, emit_report, json_destination, machine_info, npz_arrays, positive_int
from model.cli_inputs import model_dir
from service.manifest import model_folder
from service.registrar import Registrar, default_threads, session_options

PRODUCT_OPS = ("MatMul", "Gemm", "FusedGemm", "FusedMatMul")
WARM_UP = 3  # untimed calls before the timed ones (their profile events are skipped)
WIDE = 32  # a product at least this wide in its inner size and its output width is compute-bound here


class RecordingSession:
    """An ONNX Runtime session's stand-in that keeps the feeds of its first call and counts its calls."""

    def __init__(self, session: ort.InferenceSession):
        self.session, self.feeds, self.calls = session, None, 0

    def run(self, outputs: list[str] | None, feeds: dict[str, np.ndarray],
            run_options: ort.RunOptions | None = None) -> list[np.ndarray]:
        if self.feeds is None:
            self.feeds = {name: np.array(value) for name, value in feeds.items()}
        self.calls += 1
        return self.session.run(outputs, feeds, run_options)

    def __getattr__(self, name: str):
        return getattr(self.session, name)


def multiply_adds(inputs: list[list[int]], output: list[int]) -> int:
    """Multiply-adds of a matrix product from its profiled input and output shapes (``A [..., M, K]``:
    the inner size is the first input's last axis, as torch's exports write ``Gemm`` with ``transA=0``)."""
    return math.prod(output) * inputs[0][-1]


def shapes_of(entries: list[dict]) -> list[list[int]]:
    """``[{"float": [2, 768, 3]}, ...]`` (the profiler's ``input_type_shape``) -> ``[[2, 768, 3], ...]``."""
    return [next(iter(entry.values())) for entry in entries]


def profile_graph(graph: bytes, feeds: dict[str, np.ndarray], threads: int, repeats: int) -> dict:
    """Time ``graph`` on ``feeds`` (after ``WARM_UP`` calls) with the profiler on: per call and per op type."""
    options = session_options(threads)
    with tempfile.TemporaryDirectory() as folder:
        options.enable_profiling = True
        options.profile_file_prefix = str(Path(folder) / "ops")
        session = ort.InferenceSession(graph, options, providers=["CPUExecutionProvider"])
        for _ in range(WARM_UP):
            session.run(None, feeds)
        wall = [_timed(session, feeds) for _ in range(repeats)]
        events = json.loads(Path(session.end_profiling()).read_text())
    runs: dict[str, int] = defaultdict(int)  # node -> calls profiled
    per_op: dict[str, float] = defaultdict(float)  # op type -> ms over all calls
    nodes: dict[str, set[str]] = defaultdict(set)  # op type -> its nodes
    macs, wide_macs, wide_ms = 0, 0, 0.0
    for event in events:
        if event.get("cat") != "Node" or not event["name"].endswith("_kernel_time"):
            continue
        args = event["args"]
        runs[event["name"]] += 1
        if runs[event["name"]] <= WARM_UP:
            continue
        per_op[args["op_name"]] += event["dur"] / 1000
        nodes[args["op_name"]].add(event["name"])
        if args["op_name"] in PRODUCT_OPS:
            inputs, output = shapes_of(args["input_type_shape"]), shapes_of(args["output_type_shape"])[0]
            work = multiply_adds(inputs, output)
            macs += work
            if min(inputs[0][-1], output[-1]) >= WIDE:
                wide_macs, wide_ms = wide_macs + work, wide_ms + event["dur"] / 1000
    calls = max(runs.values()) - WARM_UP  # every node ran this often after the warm-up
    ops = {name: {"ms": round(ms / calls, 4), "nodes": len(nodes[name])}
           for name, ms in sorted(per_op.items(), key=lambda kv: -kv[1])}
    product_ms = sum(per_op[name] for name in PRODUCT_OPS if name in per_op)
    return {
        "ms_per_call_median": float(np.median(wall)),
        "ms_in_ops": round(sum(per_op.values()) / calls, 4),
        **_products("products", macs, product_ms, calls),
        **_products("wide_products", wide_macs, wide_ms, calls),
        "ops": ops,
    }


def _products(prefix: str, macs: int, ms: float, calls: int) -> dict:
    """``<prefix>_ms``, ``_gmac`` (per call) and ``_gflops`` of products that took ``ms`` over ``calls`` calls."""
    return {
        f"{prefix}_ms": round(ms / calls, 4),
        f"{prefix}_gmac": round(macs / calls / 1e9, 4),
        f"{prefix}_gflops": round(2 * macs / 1e9 / (ms / 1000), 1) if ms else None,
    }


def _timed(session: ort.InferenceSession, feeds: dict[str, np.ndarray]) -> float:
    tic = time.perf_counter()
    session.run(None, feeds)
    return 1000 * (time.perf_counter() - tic)


def run(pairs_path: Path, model: str, repeats: int, threads: int | None) -> dict:
    threads = threads or default_threads()
    registrar = Registrar(model_folder(model), threads=threads)
    registrar.encoder = RecordingSession(registrar.encoder)
    registrar.matchers = [RecordingSession(m) for m in registrar.matchers]
    pairs = dict(np.load(pairs_path))
    registrar.register(pairs["source"][0], pairs["target"][0], refine="none")
    graphs = {"encoder": (registrar.manifest.graph_bytes("encoder"), registrar.encoder.feeds)}
    for role, matcher in zip(registrar.manifest.matcher_roles, registrar.matchers, strict=True):
        graphs[role] = (registrar.manifest.graph_bytes(role), matcher.feeds)
    report = {name: profile_graph(graph, feeds, threads, repeats) for name, (graph, feeds) in graphs.items()}
    iterations = registrar.default_iterations
    encoder_calls = registrar.encoder.calls  # 1 with both clouds in one batch, 2 where their sizes differ
    matchers = [report[role] for role in registrar.manifest.matcher_roles]
    per_iteration = [matchers[min(i, len(matchers) - 1)] for i in range(iterations)]
    return {
        "model": model, "pairs": str(pairs_path), "repeats": repeats, "machine": machine_info(threads),
        "input_shapes": {
            name: {key: "x".join(map(str, value.shape)) for key, value in feeds.items()}
            for name, (_, feeds) in graphs.items()
        },
        "graphs": report,
        "registration": {
            "iterations": iterations,
            "encoder_calls": encoder_calls,
            "graphs_ms": round(encoder_calls * report["encoder"]["ms_per_call_median"]
                               + sum(m["ms_per_call_median"] for m in per_iteration), 3),
            **{key: round(encoder_calls * report["encoder"][key] + sum(m[key] for m in per_iteration), 3)
               for key in ("products_ms", "wide_products_ms")},
        },
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, required=True)
    parser.add_argument("--model", default="general", help="a bundled model's name or a model folder")
    parser.add_argument("--repeats", type=positive_int, default=30)
    parser.add_argument("--threads", type=positive_int, default=None, help="default: the registrar's")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    npz_arrays(parser, args.pairs)
    checked(model_dir, args.model)
    json_destination(args.json)
    emit_report(run(args.pairs, args.model, args.repeats, args.threads), args.json)


if __name__ == "__main__":
    main()
