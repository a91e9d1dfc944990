"""A real server's memory through a short session of default requests (``docs/DEPLOYMENT.md``, "Current figures")::

    python -m bench.server_memory --models general
    python -m bench.server_memory                   # every bundled model
    python -m bench.server_memory --aligned ply,pcd,las,laz,e57,npy,npz --aligned-pair laz

It starts ``mfgnet``'s HTTP app on 127.0.0.1 (``MFGNET_THREADS`` and ``MFGNET_MAX_CONCURRENCY`` 2, the server's
defaults), reads its resident memory (``VmRSS``) after start, after ``--small`` default registrations of seeded
1,024-point dense ModelNet40 test pairs, after one JSON registration of a ``--big-points`` pair (the same pair's
points and jittered copies of them), and its peak (``VmHWM``); ``searched`` counts the requests that ran the
rotation search. Every request is ``POST /v1/register`` with the two clouds as JSON and no option, so it runs what
a caller gets by default (``rotation_search: "auto"`` included).

``--aligned FORMATS`` measures the page's download instead: for each format, a fresh server (the same settings)
answers one ``POST /v1/register/aligned`` of a seeded ``--aligned-points`` file (PLY: a coloured binary mesh; PCD:
binary with intensity, normals and colour; LAS/LAZ: point format 3 with a CRS VLR; E57: a terrestrial scanner's
project of two posed scans of half the points each, as a station-by-station survey is exported, with intensity and
colour; NPY: float32 x, y, z, normals and intensity; NPZ: deflated float32 points, uint8 colours and int32 labels;
:mod:`bench.scan_files`), read to its end, and reports ``VmRSS`` after start and after the answer, and ``VmHWM``.
``--aligned-pair FORMAT`` adds two such uploads at once to a server with the Kubernetes manifest's settings
(``MFGNET_THREADS`` 1, ``MFGNET_MAX_CONCURRENCY`` 2).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

from bench import scan_files
from bench.http_latency import Server, rss_mb
from bench.latency import resize_cloud
from bench.report_io import checked, emit_report, json_destination, machine_info, non_negative_int, positive_int
from model.cli_inputs import require_shapes

SMALL_POINTS = 1024
THREADS = 2
ALIGNED_FORMATS = ("ply", "pcd", "las", "laz", "e57", "npy", "npz")
MANIFEST_THREADS, MANIFEST_CONCURRENCY = 1, 2  # deploy/k8s/deployment.yaml
# the pose sent: a quarter turn about z and a shift
ALIGNED_POSE = [[0.0, -1.0, 0.0, 1.5], [1.0, 0.0, 0.0, -2.0], [0.0, 0.0, 1.0, 0.3], [0.0, 0.0, 0.0, 1.0]]


def pairs(count: int, big_points: int, seed: int = 0) -> tuple[list[dict], dict]:
    """JSON bodies of ``count`` seeded 1,024-point dense test pairs, and one of ``big_points`` points per cloud."""
    from model.data import make_test_pairs

    test = make_test_pairs("dense", "test", count=count, seed=seed)
    rng = np.random.default_rng(seed)
    small = [
        {"source": resize_cloud(s, SMALL_POINTS, rng).tolist(), "target": resize_cloud(t, SMALL_POINTS, rng).tolist()}
        for s, t in zip(test["source"], test["target"], strict=True)
    ]
    big = {
        "source": resize_cloud(test["source"][0], big_points, rng).tolist(),
        "target": resize_cloud(test["target"][0], big_points, rng).tolist(),
    }
    return small, big


def measure(models: str | None, small_requests: int = 5, big_points: int = 100_000, seed: int = 0) -> dict:
    """Server RSS in MiB after start, after the small requests, after the big one, and its peak."""
    small, big = pairs(small_requests, big_points, seed)
    with Server(threads=THREADS, models=models) as server, httpx.Client(base_url=server.url, timeout=120) as client:

        def searched(body: dict) -> bool:
            """Register ``body``; whether the rotation search ran."""
            response = client.post("/v1/register", json=body)
            response.raise_for_status()
            return "search" in response.json()["timing_ms"]

        pid = server.proc.pid
        rss = {"after_start": rss_mb(pid)}
        searches = sum(searched(body) for body in small)
        rss["after_small"] = rss_mb(pid)
        searches += searched(big)
        rss["after_big"] = rss_mb(pid)
        rss["peak"] = rss_mb(pid, "VmHWM")
        served = [m["name"] for m in client.get("/v1/models").json()["models"]]
    return {
        "benchmark": "server_memory",
        "models": served,
        "small_requests": small_requests,
        "small_points": SMALL_POINTS,
        "searched": searches,
        "big_points": big_points,
        "seed": seed,
        "rss_mib": {k: round(v, 1) for k, v in rss.items()},
        "machine": machine_info(THREADS),
    }


def aligned_file(folder: Path, fmt: str, n: int, seed: int = 0) -> Path:
    """A seeded ``n``-point file as scanners and their users write it, in ``fmt`` (one of :data:`ALIGNED_FORMATS`): a
    coloured PLY mesh, a binary PCD with intensity, normals and colour, a LAS (or LAZ) survey in UTM coordinates, an
    E57 project of two posed scans with intensity and colour, an ``.npy`` float32 array of x, y, z, normals and
    intensity, a deflated ``.npz`` of points, colours and labels (:mod:`bench.scan_files`)."""
    xyz = np.random.default_rng(seed).random((n, 3)) * 100  # [n, 3] metres
    path = folder / f"cloud.{fmt}"
    if fmt == "ply":
        scan_files.coloured_ply(path, xyz)
    elif fmt == "pcd":
        scan_files.pcd_with_fields(path, xyz)
    elif fmt in ("las", "laz"):
        scan_files.survey_las(path, xyz + np.array([512_345.0, 4_123_456.0, 150.0]))
    elif fmt == "e57":
        scan_files.tls_e57(path, xyz)
    elif fmt == "npy":
        scan_files.ml_npy(path, xyz)
    elif fmt == "npz":
        scan_files.labelled_npz(path, xyz)
    else:
        raise ValueError(f"no aligned file of format {fmt!r} (expected one of {', '.join(ALIGNED_FORMATS)})")
    return path


def aligned_download(url: str, path: Path) -> int:
    """``POST /v1/register/aligned`` of ``path`` with :data:`ALIGNED_POSE`, its answer read to the end; its bytes."""
    with httpx.Client(base_url=url, timeout=300) as client, open(path, "rb") as f:
        files, data = {"source": (path.name, f)}, {"transform": json.dumps(ALIGNED_POSE)}
        with client.stream("POST", "/v1/register/aligned", files=files, data=data) as response:
            if response.status_code != 200:
                response.read()
                raise RuntimeError(f"{path.name}: HTTP {response.status_code}: {response.text[:300]}")
            return sum(len(chunk) for chunk in response.iter_bytes())


def aligned_memory(
    models: str | None, path: Path, at_once: int = 1, threads: int = THREADS, max_concurrency: int = THREADS
) -> dict:
    """A fresh server's RSS in MiB after start, after ``at_once`` aligned downloads of ``path`` sent together, and its
    peak; the answers' sizes in MiB."""
    with Server(threads=threads, max_concurrency=max_concurrency, models=models) as server:
        pid = server.proc.pid
        after_start = rss_mb(pid)
        with ThreadPoolExecutor(at_once) as pool:
            sizes = list(pool.map(lambda _: aligned_download(server.url, path), range(at_once)))
        rss = {"after_start": after_start, "after": rss_mb(pid), "peak": rss_mb(pid, "VmHWM")}
    rss["peak_over_start"] = rss["peak"] - after_start
    return {
        "upload_mib": round(path.stat().st_size / 2**20, 1),
        "answer_mib": round(sizes[0] / 2**20, 1),
        "at_once": at_once,
        "threads": threads,
        "max_concurrency": max_concurrency,
        "rss_mib": {k: round(v, 1) for k, v in rss.items()},
    }


def measure_aligned(models: str | None, formats: list[str], points: int, pair: str | None, seed: int = 0) -> dict:
    """:func:`aligned_memory` for one upload of each of ``formats``, in a fresh server each, and for two ``pair``
    uploads at once with the manifest's settings."""
    report = {
        "benchmark": "server_memory_aligned",
        "models": models or "every bundled model",
        "points": points,
        "seed": seed,
        "pose": ALIGNED_POSE,
        "formats": {},
    }
    with tempfile.TemporaryDirectory(prefix="mfgnet-aligned-bench-") as folder:
        for fmt in dict.fromkeys([*formats, *([pair] if pair else [])]):
            path = aligned_file(Path(folder), fmt, points, seed)
            if fmt in formats:
                report["formats"][fmt] = aligned_memory(models, path)
            if fmt == pair:
                report["pair"] = {
                    "format": pair,
                    **aligned_memory(models, path, 2, MANIFEST_THREADS, MANIFEST_CONCURRENCY),
                }
            path.unlink()
    report["machine"] = machine_info(THREADS)
    return report


def formats_list(text: str) -> list[str]:
    """``--aligned``'s comma-separated formats, each one of :data:`ALIGNED_FORMATS`."""
    names = [name.strip().lower() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in ALIGNED_FORMATS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"expected formats among {', '.join(ALIGNED_FORMATS)}, got {text!r}")
    return list(dict.fromkeys(names))


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", help="serve only these model names, comma separated (default: every bundled one)")
    parser.add_argument("--small", type=positive_int, default=5, help="1,024-point registrations before the big one")
    parser.add_argument(
        "--big-points", type=positive_int, default=100_000, help="points per cloud of the big JSON request"
    )
    parser.add_argument(
        "--aligned",
        type=formats_list,
        metavar="FORMATS",
        help="measure POST /v1/register/aligned instead: one upload per format, a fresh server each "
        f"(comma separated, of {', '.join(ALIGNED_FORMATS)})",
    )
    parser.add_argument("--aligned-points", type=positive_int, default=2_000_000, help="points of each aligned upload")
    parser.add_argument(
        "--aligned-pair",
        choices=ALIGNED_FORMATS,
        metavar="FORMAT",
        help="also two aligned uploads of FORMAT at once, with the Kubernetes manifest's settings",
    )
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args(argv)
    if args.models:
        from service.manifest import discover_model_dirs

        bundled = [folder.name for folder in discover_model_dirs([])]
        unknown = [name for name in args.models.split(",") if name.strip() not in bundled]
        if unknown:
            parser.error(f"--models: no bundled model {', '.join(unknown)} (bundled: {', '.join(bundled)})")
    json_destination(args.json)
    if args.aligned or args.aligned_pair:
        report = measure_aligned(args.models, args.aligned or [], args.aligned_points, args.aligned_pair, args.seed)
    else:
        checked(require_shapes, "test", "dense", None)  # the requests' pairs
        report = measure(args.models, args.small, args.big_points, args.seed)
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
