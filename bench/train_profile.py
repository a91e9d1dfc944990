"""Time (and optionally profile) training steps on fixed batches: ``python -m bench.train_profile``.

The figure ``mfgnet train`` logs as ``s_per_pair`` includes whatever else the machine runs; this
measures the step alone (forward, losses, backward, Adam) on pre-drawn batches after two warm-up
steps, so runs can be compared on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from bench.report_io import checked, json_destination, machine_info, positive_int, provenance
from model.allocator import keep_freed_memory
from model.cli_inputs import require_shapes
from model.config import MFGNetConfig
from model.data import TrainPairStream, load_shapes, protocol_for
from model.losses import registration_losses, sample_training_keypoints
from model.network import MFGNet


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=positive_int, default=2)
    parser.add_argument("--setting", default="noise")
    parser.add_argument("--batch-size", type=positive_int, default=8)
    parser.add_argument("--steps", type=positive_int, default=4, help="timed steps (after two warm-up steps)")
    parser.add_argument(
        "--profile",
        action="store_true",
        help="print the torch profiler's op table of one step too (with --json, store its top ops and the matrix "
        "products' share by inner size)",
    )
    parser.add_argument(
        "--compare-eager",
        action="store_true",
        help="alternate steps with the fused training layers (model.edge_fused, model.pair_fused) and eager ones",
    )
    parser.add_argument(
        "--default-allocator",
        action="store_true",
        help="keep glibc's default mmap / trim thresholds (training raises them: model.allocator)",
    )
    parser.add_argument("--data", default=None, help="ModelNet40 folder (default: MFGNET_DATA or ../shared)")
    parser.add_argument("--json", type=Path, default=None, help="also write the timings here")
    args = parser.parse_args(argv)
    checked(require_shapes, "train", args.setting, args.data)
    json_destination(args.json)

    torch.set_num_threads(args.threads)
    allocator = "default" if args.default_allocator or not keep_freed_memory() else "keep freed memory"
    shapes, _ = load_shapes("train", args.setting, args.data)
    stream = TrainPairStream(shapes[:400], protocol_for(args.setting), 0)
    batches = [batch for _, batch in zip(range(args.steps + 2), stream.epoch(0, args.batch_size), strict=False)]
    cfg = MFGNetConfig()
    model = MFGNet(cfg).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4, weight_decay=1e-3)
    generator = torch.Generator().manual_seed(0)

    def step(batch: dict[str, np.ndarray]) -> None:
        src, tgt, R, t = (torch.from_numpy(batch[k]) for k in ("source", "target", "rotation", "translation"))
        src_idx, tgt_idx = sample_training_keypoints(
            src, tgt, R, t, cfg.train_positives, cfg.train_negatives, cfg.match_threshold, generator
        )
        out = model(src, tgt, src_idx=src_idx, tgt_idx=tgt_idx)
        losses = registration_losses(out, src, tgt, R, t, cfg.match_threshold)
        optimizer.zero_grad(set_to_none=True)
        losses.total.backward()
        optimizer.step()

    for batch in batches[:2]:
        step(batch)
    variants = [True, False] if args.compare_eager else [True]
    ms: dict[bool, list[float]] = {fused: [] for fused in variants}
    faults_before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for batch in batches[2:]:
        for fused in variants:  # alternating, so both see the same machine load
            model.set_fused_training(fused)
            tic = time.perf_counter()
            step(batch)
            ms[fused].append(1000 * (time.perf_counter() - tic) / args.batch_size)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults_before) / (args.steps * len(variants))
    for fused, times in ms.items():
        layers = "fused" if fused else "eager"
        print(f"ms per training pair ({layers} layers): {[round(x, 1) for x in times]}, median "
              f"{np.median(times):.1f} ({args.threads} threads, batch {args.batch_size}, setting {args.setting})")
    print(f"minor page faults per step: {faults:.0f} (allocator: {allocator})")
    report = {}
    if args.json:
        report = {"benchmark": "train_profile", "setting": args.setting, "batch_size": args.batch_size,
                  "steps": args.steps, "allocator": allocator, "minor_page_faults_per_step": round(faults),
                  "ms_per_training_pair": {"fused" if fused else "eager": {"steps": [round(x, 2) for x in times],
                                                                           "median": round(float(np.median(times)), 2)}
                                           for fused, times in ms.items()},
                  "machine": machine_info(args.threads), "provenance": provenance([])}
    model.set_fused_training(True)
    if args.profile:
        ops = profiled_ops(step, batches[-1])
        print(ops["table"])
        if args.json:
            report["profile"] = {key: value for key, value in ops.items() if key != "table"}
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")


PRODUCTS = {"aten::mm": 0, "aten::bmm": 0, "aten::addmm": 1, "aten::addmm_": 1}  # op -> its first factor's input


def product_dims(op: str, shapes: list) -> tuple[int, int, int, int] | None:
    """``(batch, M, K, N)`` of a matrix product ``[.., M, K] x [.., K, N]`` from the profiler's input shapes of ``op``
    (one of :data:`PRODUCTS`), or ``None`` for another op or shapes it did not record."""
    if op not in PRODUCTS or len(shapes) < PRODUCTS[op] + 2:
        return None
    a, b = shapes[PRODUCTS[op]], shapes[PRODUCTS[op] + 1]
    if len(a) < 2 or len(b) < 2 or a[-1] != b[-2]:
        return None
    return int(np.prod(a[:-2], dtype=np.int64)), int(a[-2]), int(a[-1]), int(b[-1])


def profiled_ops(step: Callable[[dict[str, np.ndarray]], None], batch: dict[str, np.ndarray], rows: int = 30) -> dict:
    """One ``step`` of ``batch`` under torch's profiler: the op table (``table``), the ``rows`` ops with the most self
    CPU time by input shape (``ops``), and the matrix products' share of the step by width (``products_by_width``: the
    narrowest of a product's M, K and N, so that a layer's forward product and its gradients count together). No
    rates: the profiler records shapes, not layouts, and a sparse product (the fused edge layer's scatter) would
    count as a dense one."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        step(batch)
    averages = prof.key_averages(group_by_input_shape=True)
    total_us = sum(event.self_cpu_time_total for event in averages)

    def summary(us: float) -> dict:
        return {"self_cpu_ms": round(us / 1000, 3), "share": round(us / total_us, 4)}

    ops = [{"op": event.key, "input_shapes": str(event.input_shapes), "calls": event.count,
            **summary(event.self_cpu_time_total)}
           for event in sorted(averages, key=lambda event: event.self_cpu_time_total, reverse=True)[:rows]]
    by_width: dict[int, float] = {}
    for event in averages:
        dims = product_dims(event.key, event.input_shapes)
        if dims is not None:
            by_width[min(dims[1:])] = by_width.get(min(dims[1:]), 0.0) + event.self_cpu_time_total
    return {
        "table": averages.table(sort_by="self_cpu_time_total", row_limit=rows),
        "self_cpu_ms": round(total_us / 1000, 3),
        "products_by_width": {str(width): summary(us) for width, us in sorted(by_width.items())},
        "ops": ops,
    }


if __name__ == "__main__":
    main()
