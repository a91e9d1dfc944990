"""End-to-end HTTP latency and throughput against a real server on 127.0.0.1 (used by ``mfgnet bench``).

Run alone, it measures what HTTP adds to the in-process pipeline (docs/BENCHMARKS.md, "HTTP overhead")::

    python -m bench.http_latency --requests 40 --big-requests 3 --json overhead.json
    python -m bench.http_latency --compare-root /tmp/old-checkout   # and a server from another checkout

The same seeded 768-point ModelNet40 pairs go through ``Registrar.register`` in this process and
through ``POST /v1/register`` (JSON, one client thread), then 20k/100k-point pairs; each server's
RSS is read from ``/proc`` after each phase. ``json`` rows include the client's own JSON encoding
(httpx ``json=``, as ``mfgnet bench`` does); ``bytes`` rows send bodies encoded beforehand (server
and transport only). ``beyond_pipeline`` is, per request, the client's time minus the server's own
``timing_ms`` (pipeline total and queue), so it holds up when the machine's load drifts between the
in-process and the HTTP calls. With ``--compare-root`` the servers run side by side and take turns.
"""

from __future__ import annotations

import atexit
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import httpx
import numpy as np

CONCURRENCY = (1, 2, 4, 8)
# The network pipeline alone, as the in-process figures it is compared with (the server's default adds icp-plane).
NETWORK_ONLY = {"refine": "none"}


_RUNNING: set[subprocess.Popen] = set()  # the servers this process started and has not stopped yet
_sigterm_before: list = []  # SIGTERM's handler before the first of them started, while it is replaced
_unraisable_before: list = []  # sys.unraisablehook before the first of them started, while it is replaced
_holding: list[bool] = []  # not empty while a server is being started and registered (_holding_signals)
_held: list[int] = []  # SIGTERM or SIGINT arrived then


class _Terminated(SystemExit):
    """What SIGTERM raises while servers run (:func:`_exit_on_sigterm`)."""


def _exit_on_sigterm(signum: int, frame: object) -> None:
    if _holding:
        _held.append(signum)
        return
    raise _Terminated(128 + signum)  # the shell's status of a process that signal ended


def _hold(signum: int, frame: object) -> None:
    _held.append(signum)


@contextmanager
def _holding_signals() -> Iterator[None]:
    """SIGTERM (ours) and Ctrl-C's SIGINT held back while a server is started and put in ``_RUNNING``: raised between
    its fork and the end of ``Popen``, the exception would leave a server that no ``with`` block and no ``atexit``
    handler knows of. Raised once it is registered."""
    sigint = (threading.current_thread() is threading.main_thread()
              and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
    if sigint:
        signal.signal(signal.SIGINT, _hold)
    _holding.append(True)
    try:
        yield
    finally:
        _holding.pop()
        if sigint:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    if _held:
        signum = _held[0]
        _held.clear()
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise _Terminated(128 + signum)


def _deliver_again(unraisable: sys.UnraisableHookArgs) -> None:
    """``sys.unraisablehook`` while servers run. Python runs a signal's handler wherever the main thread is, in a
    finalizer or a weakref callback too (importlib runs one after each import: the first ``httpx.Client`` imports some
    130 modules while the server starts; ``Popen.__del__``), and only prints what it raises there: SIGTERM's exit or
    Ctrl-C's KeyboardInterrupt would be lost, and the benchmark would run on to its end and exit 0. That signal is sent
    again once the main thread has left the callback; anything else is reported as before."""
    exc = unraisable.exc_value
    signum = (signal.SIGTERM if isinstance(exc, _Terminated) else
              signal.SIGINT if isinstance(exc, KeyboardInterrupt) else None)
    if signum is None:
        _unraisable_before[0](unraisable)
    else:
        threading.Timer(0.05, os.kill, (os.getpid(), signum)).start()


def _catch_sigterm() -> None:
    """While servers run, SIGTERM ends this process as Ctrl-C does, through its ``with`` blocks (which stop them and
    remove their temporary files), instead of at once, leaving them running. Only from the main thread, and only in
    place of the default action (never over a handler someone else set)."""
    if (not _sigterm_before and threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL):
        _sigterm_before.append(signal.signal(signal.SIGTERM, _exit_on_sigterm))
        _unraisable_before.append(sys.unraisablehook)
        sys.unraisablehook = _deliver_again


def _release_sigterm() -> None:
    """SIGTERM's own handler back, once no server of this process runs."""
    if _sigterm_before and not _RUNNING and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _sigterm_before.pop())
        sys.unraisablehook = _unraisable_before.pop()


def _stop(proc: subprocess.Popen) -> None:
    """End ``proc``: SIGTERM (uvicorn's graceful shutdown), SIGKILL after 30 s."""
    proc.terminate()
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    _RUNNING.discard(proc)


@atexit.register
def _stop_running() -> None:
    """At exit, every server still running (one made but never entered, or one whose start an interrupt cut short)."""
    for proc in list(_RUNNING):
        _stop(proc)


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
    """``mfgnet``'s HTTP app in a subprocess on a free loopback port (one uvicorn process), stopped when the ``with``
    block ends, its start fails or is interrupted, and on SIGTERM (:func:`_catch_sigterm`)."""

    def __init__(self, threads: int = 2, max_concurrency: int = 2, max_queue: int = 64, cwd: str | None = None,
                 model_dirs: str | None = None, default_model: str | None = None, models: str | None = None,
                 timeout_s: float | None = None):
        self.port = free_port()
        env = {**os.environ, "MFGNET_HOST": "127.0.0.1", "MFGNET_PORT": str(self.port),
               "MFGNET_THREADS": str(threads), "MFGNET_MAX_CONCURRENCY": str(max_concurrency),
               "MFGNET_MAX_QUEUE": str(max_queue), "MFGNET_LOG_LEVEL": "warning"}
        if model_dirs:  # serve exactly these models (not the bundled ones of the checkout that runs)
            env.update(MFGNET_MODEL_DIRS=model_dirs, MFGNET_BUNDLED_MODELS="false")
        if default_model:  # what a request naming no model gets
            env["MFGNET_DEFAULT_MODEL"] = default_model
        if models:  # serve only these model names (comma separated)
            env["MFGNET_MODELS"] = models
        if timeout_s is not None:  # the deadline per request
            env["MFGNET_TIMEOUT_S"] = str(timeout_s)
        if cwd:  # "-c" puts the working directory first on sys.path: that checkout's service package runs
            env["PYTHONPATH"] = cwd
        _catch_sigterm()
        with _holding_signals():
            self.proc = subprocess.Popen([sys.executable, "-c", "from service.api.app import run_server; run_server()"],
                                         env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            _RUNNING.add(self.proc)
        self.url = f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> Server:
        deadline = time.time() + 120
        try:
            with httpx.Client(timeout=5) as client:
                while time.time() < deadline:
                    try:
                        if client.get(self.url + "/v2/health/ready").status_code == 200:
                            return self
                    except httpx.TransportError:
                        pass
                    time.sleep(0.2)
        except BaseException:  # Ctrl-C or SIGTERM while it starts: no with block will stop it
            self.__exit__()
            raise
        self.__exit__()
        raise RuntimeError("benchmark server did not become ready")

    def __exit__(self, *exc) -> None:
        _stop(self.proc)
        _release_sigterm()


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
    bodies = [{"source": s.tolist(), "target": t.tolist(), **NETWORK_ONLY}
              for s, t in zip(pairs["source"], pairs["target"], strict=True)]
    with Server(threads=threads) as server:
        rss_before = rss_mb(server.proc.pid)
        report = {"rss_mb_after_start": rss_before,
                  "load_768": [run_load(server.url, bodies, c, requests) for c in CONCURRENCY]}
        report["sizes"] = {name: run_load(server.url, [{"source": s.tolist(), "target": t.tolist(), **NETWORK_ONLY}], 1,
                                          max(3, requests // 10))
                           for name, (s, t) in sized.items()}
        report["rss_mb_end"] = rss_mb(server.proc.pid)
        report["rss_mb_peak"] = rss_mb(server.proc.pid, "VmHWM")
    return report


# -- python -m bench.http_latency: what HTTP adds to the in-process pipeline --------------------------
def _p50(samples: list[float]) -> float:
    return float(np.percentile(samples, 50))


def bench_overhead(requests: int = 40, big_requests: int = 3, threads: int = 2,
                   server_roots: tuple[str | None, ...] = (None,), seed: int = 0) -> dict:
    """In-process vs HTTP p50 on 768-point pairs, 20k/100k-point JSON requests, and each server's RSS.

    Several servers (``server_roots``: checkouts, ``None`` = this one) run side by side and every
    round sends the same request to each in turn, after one in-process call: a busy machine slows
    all of them alike, so their differences stay fair.
    """
    import json
    import shutil
    import tempfile
    from contextlib import ExitStack
    from pathlib import Path

    from bench.latency import LARGE_INPUTS, resize_cloud
    from model.data import make_test_pairs
    from service.manifest import bundled_models_dir
    from service.registrar import Registrar

    models = Path(tempfile.mkdtemp(prefix="mfgnet-bench-http-"))
    shutil.copytree(bundled_models_dir() / "clean", models / "clean")  # one model for every side
    try:
        pairs = make_test_pairs("clean", "test", count=16, seed=seed)
        sources, targets = list(pairs["source"]), list(pairs["target"])
        registrar = Registrar(models / "clean", threads=threads)
        bodies = [{"source": s.tolist(), "target": t.tolist(), **NETWORK_ONLY}
                  for s, t in zip(sources, targets, strict=True)]
        encoded = [json.dumps(b).encode() for b in bodies]
        rng = np.random.default_rng(0)
        big = {n: {"source": resize_cloud(sources[0], n, rng).tolist(),
                   "target": resize_cloud(targets[0], n, rng).tolist(), **NETWORK_ONLY} for n in LARGE_INPUTS}
        headers = {"content-type": "application/json"}
        with ExitStack() as stack:
            servers = [stack.enter_context(Server(threads=threads, cwd=root, model_dirs=str(models)))
                       for root in server_roots]
            clients = [stack.enter_context(httpx.Client(base_url=s.url, timeout=120)) for s in servers]
            reports: list[dict] = [{"server_root": root or "(this checkout)",
                                    "rss_mb_after_start": rss_mb(s.proc.pid)} for root, s in
                                   zip(server_roots, servers, strict=True)]

            def timed(client: httpx.Client, **kwargs) -> tuple[float, float]:
                """Client-side ms of one request, and that minus the server's own pipeline ms (``timing_ms``)."""
                tic = time.perf_counter()
                response = client.post("/v1/register", **kwargs)
                elapsed = 1000 * (time.perf_counter() - tic)
                if response.status_code != 200:
                    raise RuntimeError(f"{response.status_code}: {response.text[:300]}")
                timing = response.json()["timing_ms"]
                return elapsed, elapsed - timing["total"] - timing["queue"]

            def rounds(count: int, kinds: dict, warmup: int = 1) -> dict[str, list[list[tuple[float, float]]]]:
                """``kinds``: name -> (i -> request kwargs); each round times every kind on every server."""
                times: dict = {kind: [[] for _ in servers] for kind in kinds}
                for i in range(-warmup, count):
                    for kind, make in kinds.items():
                        for k, client in enumerate(clients):
                            measured = timed(client, **make(i))
                            if i >= 0:
                                times[kind][k].append(measured)
                return times

            in_process: list[float] = []
            registrar.register(sources[0], targets[0])
            for i in range(requests):
                tic = time.perf_counter()
                registrar.register(sources[i % len(sources)], targets[i % len(targets)])
                in_process.append(1000 * (time.perf_counter() - tic))
                rounds(1, {"json": lambda _, i=i: {"json": bodies[i % len(bodies)]}}, warmup=0)  # interleave
            small = rounds(requests, {
                "json": lambda i: {"json": bodies[i % len(bodies)]},
                "bytes": lambda i: {"content": encoded[i % len(encoded)], "headers": headers},
            })
            report: dict = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "threads": threads,
                            "in_process_768_p50_ms": _p50(in_process)}
            for k, server in enumerate(servers):
                r = reports[k]
                for kind in ("json", "bytes"):
                    r[f"http_768_{kind}_p50_ms"] = _p50([t for t, _ in small[kind][k]])
                    r[f"overhead_768_{kind}_ms"] = r[f"http_768_{kind}_p50_ms"] - report["in_process_768_p50_ms"]
                    r[f"beyond_pipeline_768_{kind}_p50_ms"] = _p50([extra for _, extra in small[kind][k]])
                r["rss_mb_after_768"] = rss_mb(server.proc.pid)
            for n, body in big.items():
                raw = json.dumps(body).encode()
                sized = rounds(big_requests, {"json": lambda _, body=body: {"json": body},
                                              "bytes": lambda _, raw=raw: {"content": raw, "headers": headers}})
                for k, server in enumerate(servers):
                    for kind in ("json", "bytes"):
                        reports[k][f"http_{n}_{kind}_p50_ms"] = _p50([t for t, _ in sized[kind][k]])
                        reports[k][f"beyond_pipeline_{n}_{kind}_p50_ms"] = _p50([extra for _, extra in sized[kind][k]])
                    reports[k][f"rss_mb_after_{n}"] = rss_mb(server.proc.pid)
                report[f"body_{n}_mib"] = len(raw) / 2**20
            for k, server in enumerate(servers):
                reports[k]["rss_mb_peak"] = rss_mb(server.proc.pid, "VmHWM")
            report["servers"] = reports
    finally:
        shutil.rmtree(models, ignore_errors=True)
    return report


def main(argv: list[str] | None = None) -> None:
    import argparse
    import json

    from bench.report_io import checked, json_destination, machine_info, positive_int, provenance, require_checkouts
    from model.cli_inputs import require_shapes
    from service.manifest import bundled_models_dir

    parser = argparse.ArgumentParser(description="What HTTP adds to the in-process pipeline (see module docstring).")
    parser.add_argument("--requests", type=positive_int, default=40, help="timed 768-point rounds")
    parser.add_argument("--big-requests", type=positive_int, default=3, help="timed rounds per 20k/100k size")
    parser.add_argument("--threads", type=positive_int, default=2, help="ONNX Runtime threads (in process and servers)")
    parser.add_argument("--compare-root", action="append", default=[],
                        help="also serve from this checkout, side by side (repeatable)")
    parser.add_argument("--json", help="also write the report here")
    args = parser.parse_args(argv)
    checked(require_shapes, "test", "clean", None)  # the 768-point pairs
    json_destination(args.json)
    require_checkouts(parser, args.compare_root)
    # before the run: the checkout may move on during it; --compare-root servers run their roots' code
    made_by = provenance([bundled_models_dir() / "clean"])  # the model every server gets
    report = {**bench_overhead(args.requests, args.big_requests, args.threads, (None, *args.compare_root)),
              "machine": machine_info(args.threads), "provenance": made_by}
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
