"""Peak server memory with every slot taken by a JSON request of the largest accepted body (``docs/DEPLOYMENT.md``,
"Current figures")::

    python -m bench.queued_bodies                         # the manifest's settings
    python -m bench.queued_bodies --compare-root ../old   # and another checkout's server, in the same run
    python -m bench.queued_bodies --beside-aligned laz    # the queue filled while both workers write aligned files

It starts ``mfgnet``'s HTTP app on 127.0.0.1 with the deployment manifest's settings (every bundled model,
``MFGNET_THREADS`` 1, ``MFGNET_MAX_CONCURRENCY`` 2, the default ``max_queue`` 16, ``max_body_bytes`` and
``max_buffered_bytes``), registers one small pair, then sends ``max_concurrency + max_queue`` requests at once, each
a ``max_points``-point pair (seeded, jittered copies of a ModelNet40 test pair) padded with spaces to
``max_body_bytes``, and reads the server's peak resident memory (``VmHWM``). With ``--beside-aligned FORMAT``, both
workers first take an aligned download (``POST /v1/register/aligned``) of a 2,000,000-point file of that format
(:func:`bench.server_memory.aligned_file`), and the queue is filled (``max_queue`` requests) once both run.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

from bench.http_latency import Server, rss_mb
from bench.report_io import checked, emit_report, json_destination, machine_info, require_checkouts
from bench.server_memory import ALIGNED_FORMATS, aligned_download, aligned_file, pairs
from model.cli_inputs import require_shapes
from service.core.config import Settings

THREADS, MAX_CONCURRENCY = 1, 2  # deploy/k8s/deployment.yaml


def padded_body(points: int, size: int) -> bytes:
    """A JSON ``/v1/register`` body of ``points`` points per cloud, padded with spaces to ``size`` bytes."""
    _, big = pairs(1, points)
    body = json.dumps(big).encode()
    if len(body) > size:
        raise ValueError(f"{points} points take {len(body)} bytes, above {size}")
    return body + b" " * (size - len(body))


def measure(cwd: str | None, body: bytes, small: dict, requests: int, aligned: Path | None = None) -> dict:
    """Peak RSS (MiB) after one small request and after ``requests`` of ``body`` at once (with ``aligned``, sent once
    both workers run an aligned download of that file); their statuses."""
    max_queue = requests if aligned else requests - MAX_CONCURRENCY
    with Server(threads=THREADS, max_concurrency=MAX_CONCURRENCY, max_queue=max_queue, cwd=cwd, timeout_s=300
                ) as server, ThreadPoolExecutor(MAX_CONCURRENCY) as downloads:
        with httpx.Client(base_url=server.url, timeout=300) as client:
            client.post("/v1/register", json=small).raise_for_status()
        warm = rss_mb(server.proc.pid, "VmHWM")

        def send(_: int) -> int:
            with httpx.Client(base_url=server.url, timeout=300) as client:
                return client.post("/v1/register", content=body,
                                   headers={"content-type": "application/json"}).status_code

        started = time.perf_counter()
        moved = []  # the aligned downloads that hold the workers
        if aligned:
            moved = [downloads.submit(aligned_download, server.url, aligned) for _ in range(MAX_CONCURRENCY)]
            wait_until_running(server.url, MAX_CONCURRENCY)
        with ThreadPoolExecutor(requests) as pool:
            statuses = list(pool.map(send, range(requests)))
        for download in moved:
            download.result()
        seconds = time.perf_counter() - started
        peak = rss_mb(server.proc.pid, "VmHWM")
    return {"peak_after_warm_up_mib": round(warm, 1), "peak_mib": round(peak, 1), "seconds": round(seconds, 1),
            "statuses": {str(s): statuses.count(s) for s in sorted(set(statuses))},
            **({"aligned_downloads": len(moved)} if aligned else {})}


def wait_until_running(url: str, count: int, timeout_s: float = 120.0) -> None:
    """Until the server at ``url`` reports ``count`` registrations (or aligned downloads) running in its workers."""
    deadline = time.perf_counter() + timeout_s
    with httpx.Client(base_url=url, timeout=10) as client:
        while time.perf_counter() < deadline:
            for line in client.get("/metrics").text.splitlines():
                if line.startswith("mfgnet_inference_running ") and float(line.split()[1]) >= count:
                    return
            time.sleep(0.05)
    raise RuntimeError(f"the server did not run {count} requests within {timeout_s:g} s")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--compare-root", help="also measure the server of the checkout in this folder")
    parser.add_argument("--json", type=Path, help="also write the report here")
    parser.add_argument("--beside-aligned", choices=ALIGNED_FORMATS, metavar="FORMAT",
                        help="fill the queue while both workers write an aligned download of a 2,000,000-point file "
                             f"of this format ({', '.join(ALIGNED_FORMATS)})")
    args = parser.parse_args(argv)
    checked(require_shapes, "test", "dense", None)  # the small request's pair
    json_destination(args.json)
    require_checkouts(parser, args.compare_root)
    settings = Settings()
    requests = MAX_CONCURRENCY + settings.max_queue
    body = padded_body(settings.max_points, settings.max_body_bytes)
    small, _ = pairs(1, 32)
    with tempfile.TemporaryDirectory(prefix="mfgnet-queued-bench-") as folder:
        aligned = aligned_file(Path(folder), args.beside_aligned, settings.max_file_points) if args.beside_aligned \
            else None
        if aligned:
            requests = settings.max_queue  # the workers are taken by the downloads
        report = {"benchmark": "queued_bodies", "requests": requests, "points": settings.max_points,
                  "body_bytes": len(body), "max_buffered_bytes": settings.max_buffered_bytes,
                  "beside_aligned": args.beside_aligned,
                  "this": measure(None, body, small[0], requests, aligned), "machine": machine_info(THREADS)}
        if args.compare_root:
            report["compared"] = measure(args.compare_root, body, small[0], requests, aligned)
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
