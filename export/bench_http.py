"""End-to-end HTTP latency and throughput against a real server on 127.0.0.1 (used by ``mfgnet bench``)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np

CONCURRENCY = (1, 2, 4, 8)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int, field: str = "VmRSS") -> float:
    """Resident (``VmRSS``) or peak (``VmHWM``) memory of a process in MiB, from ``/proc``."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


class Server:
    """``mfgnet``'s HTTP app in a subprocess on a free loopback port (one uvicorn process)."""

    def __init__(self, threads: int = 2, max_concurrency: int = 2, max_queue: int = 64):
        self.port = free_port()
        env = {**os.environ, "MFGNET_HOST": "127.0.0.1", "MFGNET_PORT": str(self.port),
               "MFGNET_THREADS": str(threads), "MFGNET_MAX_CONCURRENCY": str(max_concurrency),
               "MFGNET_MAX_QUEUE": str(max_queue), "MFGNET_LOG_LEVEL": "warning"}
        self.proc = subprocess.Popen([sys.executable, "-c", "from service.api.app import run_server; run_server()"],
                                     env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.url = f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> Server:
        deadline = time.time() + 120
        with httpx.Client(timeout=5) as client:
            while time.time() < deadline:
                try:
                    if client.get(self.url + "/v2/health/ready").status_code == 200:
                        return self
                except httpx.TransportError:
                    pass
                time.sleep(0.2)
        self.__exit__()
        raise RuntimeError("benchmark server did not become ready")

    def __exit__(self, *exc) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=30)


def run_load(url: str, bodies: list[dict], concurrency: int, requests: int) -> dict:
    """``requests`` registrations with ``concurrency`` client threads: latency percentiles, throughput."""
    latencies: list[float] = []
    statuses: dict[int, int] = {}

    def one(i: int, client: httpx.Client) -> None:
        tic = time.perf_counter()
        status = client.post(url + "/v1/register", json=bodies[i % len(bodies)]).status_code
        latencies.append(1000 * (time.perf_counter() - tic))
        statuses[status] = statuses.get(status, 0) + 1

    with httpx.Client(timeout=120, limits=httpx.Limits(max_connections=concurrency)) as client:
        one(0, client)  # warm the connection
        latencies.clear()
        statuses.clear()
        begin = time.perf_counter()
        with ThreadPoolExecutor(concurrency) as pool:
            list(pool.map(lambda i: one(i, client), range(requests)))
        seconds = time.perf_counter() - begin
    a = np.asarray(latencies)
    return {"concurrency": concurrency, "requests": requests, "statuses": statuses,
            "p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95)),
            "p99_ms": float(np.percentile(a, 99)), "throughput_rps": requests / seconds}


def bench_http(pairs: dict[str, np.ndarray], requests: int, sized: dict[str, tuple[np.ndarray, np.ndarray]],
               threads: int = 2) -> dict:
    """Latency at concurrency 1/2/4/8 on 768-point pairs, single requests of other sizes, server RSS."""
    bodies = [{"source": s.tolist(), "target": t.tolist()} for s, t in zip(pairs["source"], pairs["target"],
                                                                            strict=True)]
    with Server(threads=threads) as server:
        rss_before = rss_mb(server.proc.pid)
        report = {"rss_mb_after_start": rss_before,
                  "load_768": [run_load(server.url, bodies, c, requests) for c in CONCURRENCY]}
        report["sizes"] = {name: run_load(server.url, [{"source": s.tolist(), "target": t.tolist()}], 1,
                                          max(3, requests // 10))
                           for name, (s, t) in sized.items()}
        report["rss_mb_end"] = rss_mb(server.proc.pid)
        report["rss_mb_peak"] = rss_mb(server.proc.pid, "VmHWM")
    return report
