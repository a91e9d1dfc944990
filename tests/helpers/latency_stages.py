"""Latency ratios: each pipeline stage's time divided by a fixed reference workload timed in the same
run. Absolute times vary between machines; these ratios much less.

Refresh the committed baseline (on a quiet machine) with::

    python tests/helpers/latency_stages.py --write tests/latency/baseline.json
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "helpers"))  # run as a script, too
from shapes import bumpy_ellipsoid

REPEATS = 15
REFERENCE_SIZE = 192  # the reference: a float32 192x192 matrix product, repeated
REFERENCE_LOOPS = 60  # ~15 ms: long enough to time stably


def best_of(fn: Callable[[], object], repeats: int = REPEATS) -> float:
    """Fastest of ``repeats`` timed calls in seconds (robust to a busy machine), after one warm-up."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - tic)
    return best


def reference_seconds() -> float:
    a = np.random.default_rng(0).standard_normal((REFERENCE_SIZE, REFERENCE_SIZE)).astype(np.float32)

    def work():
        x = a
        for _ in range(REFERENCE_LOOPS):
            x = np.tanh(x @ a)
        return x

    return best_of(work)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def http_seconds(src: np.ndarray, tgt: np.ndarray) -> float:
    """Best-of time of one JSON ``POST /v1/register`` against a real server on 127.0.0.1."""
    import httpx

    port = free_port()
    env = {**os.environ, "MFGNET_PORT": str(port), "MFGNET_HOST": "127.0.0.1", "MFGNET_THREADS": "1"}
    code = "from service.api.app import run_server; run_server()"
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        url = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=url, timeout=30) as client:
            deadline = time.time() + 90
            while time.time() < deadline:
                try:
                    if client.get("/v2/health/ready").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.2)
            else:
                raise RuntimeError("server did not become ready")
            body = {"source": src.tolist(), "target": tgt.tolist(), "refine": "none"}  # = register_in_process
            return best_of(lambda: client.post("/v1/register", json=body).raise_for_status())
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def measure(include_http: bool = True) -> dict[str, float]:
    """Ratio of every stage to the reference workload (both timed now, on this machine)."""
    from service.manifest import bundled_models_dir
    from service.normalization import Normalization
    from service.procrustes import weighted_procrustes
    from service.registrar import Registrar
    from service.sampling import resample_indices

    registrar = Registrar(bundled_models_dir() / "clean", threads=1)
    src, tgt = bumpy_ellipsoid(768, 0, np.float32), bumpy_ellipsoid(768, 1, np.float32) + 0.1
    big = bumpy_ellipsoid(5000, 2, np.float32)
    both = np.stack([src, tgt])
    emb, _ = registrar.embed(both)
    kp = np.arange(128)
    ps, pt = src[None, kp], tgt[None, kp]
    fs, ft = emb[:1, kp], emb[1:, kp]
    w = np.random.default_rng(0).uniform(size=128)

    def preprocess():
        idx = resample_indices(big, 768, drop_isolated=True)  # as Registrar.register does by default
        norm = Normalization.fit(big[idx], big[idx], 0.5)
        return norm.apply_src(big[idx])

    stages = {
        "encoder": lambda: registrar.embed(both),
        "one_iteration": lambda: registrar.match(0, ps, pt, fs, ft),
        "svd": lambda: weighted_procrustes(ps[0].astype(np.float64), pt[0].astype(np.float64), w),
        "preprocessing": preprocess,
        "register_in_process": lambda: registrar.register(src, tgt),
    }
    ref = reference_seconds()
    ratios = {name: best_of(fn) / ref for name, fn in stages.items()}
    if include_http:
        ratios["register_http"] = http_seconds(src, tgt) / ref
    ratios["reference_ms"] = 1000 * ref
    return ratios


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", type=Path, help="write the measured ratios as the new baseline")
    args = parser.parse_args()
    result = measure()
    text = json.dumps(result, indent=2)
    print(text)
    if args.write:
        args.write.write_text(text + "\n")
