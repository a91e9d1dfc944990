"""How the ``python -m bench.*`` experiments hand back their report: printed, and saved when asked."""

from __future__ import annotations

import json
from pathlib import Path


def emit_report(report: dict, json_path: Path | None) -> None:
    """Print ``report`` as indented JSON and, with ``json_path``, write the same text there."""
    text = json.dumps(report, indent=2)
    print(text)
    if json_path:
        json_path.write_text(text + "\n")


def reliable_totals(rows: list[dict]) -> dict:
    """Cases, successes, ``reliable`` results given and wrong, their precision (the share of those given that are
    right) and coverage (the share of the successes given it) of ``rows`` (each with ``success`` and ``reliable``)."""
    right = sum(r["success"] for r in rows)
    given = sum(r["reliable"] for r in rows)
    wrong = sum(r["reliable"] and not r["success"] for r in rows)
    return {"cases": len(rows), "successes": right, "reliable_given": given, "reliable_wrong": wrong,
            "precision": round((given - wrong) / given, 4) if given else None,
            "coverage": round((given - wrong) / right, 4) if right else None}


VECTOR_EXTENSIONS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_tile")  # what GEMM speed hangs on


def machine_info(threads: int) -> dict:
    """Where a benchmark ran: platform, CPU model, its vector extensions (the development VM's host
    changes between sessions, with or without AVX-512), logical CPUs and the threads used."""
    import os
    import platform

    info = {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
            "threads": threads}
    try:
        cpuinfo = Path("/proc/cpuinfo").read_text()
    except OSError:
        return info
    fields = dict(line.split(":", 1) for line in cpuinfo.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    flags = set(fields.get("flags", "").split())
    info["cpu_model"] = fields.get("model name", "")
    info["vector_extensions"] = [f for f in VECTOR_EXTENSIONS if f in flags]
    return info
