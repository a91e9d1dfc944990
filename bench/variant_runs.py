"""In-process runs of made-up variants of real pairs: the service's defaults beside FPFH + RANSAC + ICP.

Shared by :mod:`bench.lidar_variants` and :mod:`bench.altered_scans`: each case is registered by the bundled
``general`` model with the service's defaults (``refine="icp-plane"``, ``rotation_search="auto"``) and, unless left
out, by :func:`bench.real_scans.fpfh_ransac_icp`; success by the data README's thresholds for the case's sensor.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from bench.real_scans import fpfh_ransac_icp, fpfh_threads, pose_errors, thresholds
from bench.report_io import machine_info, reliable_totals
from service.manifest import bundled_models_dir
from service.registrar import Registrar, default_threads


def general_registrar() -> Registrar:
    """The bundled ``general`` model's registrar."""
    return Registrar(bundled_models_dir() / "general")


def registered(cases: Iterable[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]], fpfh: bool = True,
               registrar: Registrar | None = None,
               guess: Callable[[np.ndarray], np.ndarray] | None = None) -> list[dict]:
    """One row per ``(label, sensor, source [N, 3], target [M, 3], src_to_tgt [4, 4])`` case (printed as it comes):
    errors, success, ``reliable``, inlier ratio, warnings and seconds of the service (``registrar``, default
    :func:`general_registrar`), and FPFH + RANSAC + ICP's success and seconds. ``guess``: the service's
    ``initial_transform [4, 4]`` for a case's truth (none without it; FPFH + RANSAC + ICP never takes one)."""
    registrar = general_registrar() if registrar is None else registrar
    rows = []
    for label, sensor, src, tgt, truth, *own in cases:
        max_deg, max_error = own[0] if own and own[0] is not None else thresholds(sensor)  # the pair file's first
        options = {} if guess is None else {"initial_transform": guess(truth)}
        started = time.perf_counter()
        result = registrar.register(src, tgt, refine="icp-plane", rotation_search="auto", **options)
        seconds = time.perf_counter() - started
        degrees, error = pose_errors(result.rotation, result.translation, truth)
        row = {"variant": label, "service_success": bool(degrees < max_deg and error < max_error),
               "reliable": bool(result.reliable), "rotation_error_deg": round(degrees, 3),
               "translation_error": float(f"{error:.4g}"), "service_seconds": round(seconds, 4),
               "inlier_ratio": round(float(result.inlier_ratio), 3), "warnings": list(result.warnings)}
        if fpfh:
            started = time.perf_counter()
            R, t = fpfh_ransac_icp(src, tgt)
            row["fpfh_seconds"] = round(time.perf_counter() - started, 4)
            row["fpfh_success"] = bool(np.less(pose_errors(R, t, truth), (max_deg, max_error)).all())
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def totals(rows: list[dict]) -> dict:
    """Cases, successes, ``reliable`` given and wrong, and seconds of ``rows`` (FPFH + RANSAC + ICP's where run)."""
    counts = reliable_totals([{"success": r["service_success"], "reliable": r["reliable"]} for r in rows])
    out = {"cases": counts["cases"], "service_successes": counts["successes"],
           "reliable_given": counts["reliable_given"], "reliable_wrong": counts["reliable_wrong"],
           "service_seconds": round(sum(r["service_seconds"] for r in rows), 2)}
    if rows and "fpfh_success" in rows[0]:
        out |= {"fpfh_successes": sum(r["fpfh_success"] for r in rows),
                "fpfh_seconds": round(sum(r["fpfh_seconds"] for r in rows), 2)}
    return out


def report(benchmark: str, groups: dict[str, list[dict]], json_path: Path | None, made_by: dict | None = None) -> dict:
    """The totals of each group of rows (printed), written with every row, the machine and ``made_by`` (what made
    them: :func:`bench.report_io.provenance`, taken before the run) to ``json_path`` when given."""
    summary = {name: totals(rows) for name, rows in groups.items()}
    for name, figures in summary.items():
        print(name, json.dumps(figures))
    rows = [r for group in groups.values() for r in group]
    machine = machine_info(default_threads())  # threads: the service's
    if any("fpfh_success" in r for r in rows):
        machine["fpfh_threads"] = fpfh_threads()  # FPFH + RANSAC + ICP's, beside
    result = {"benchmark": benchmark, "totals": summary, "machine": machine,
              **({"provenance": made_by} if made_by is not None else {}),
              "rows": rows}
    if json_path:
        json_path.write_text(json.dumps(result, indent=1))
    return result
