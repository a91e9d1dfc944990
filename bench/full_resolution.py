"""Clouds of 2,000,000 points, the file uploads' limit: registration time, server memory, upload and parse time
(``docs/REAL_SCANS.md``, "Full-resolution clouds"; ``docs/DEPLOYMENT.md``, "Current figures")::

    python -m bench.full_resolution --json results/general-0.2.0/full_resolution.json

The pair is the full-resolution test's (``tests/service/test_api_full_resolution.py``): two independent samples of
a smooth asymmetric surface (:func:`model.analytic_shapes.asymmetric_blob`), the target turned and shifted. Each part
runs ``--runs`` times:

- ``in_process``: a fresh process registers the pair with :class:`service.in_process.LocalRegistrar` and no option
  (``general``, its default threads) ``--repeats`` + 1 times; the first call is left out. Seconds per call, the
  rotation error, ``reliable``, and whether the rotation search ran.
- ``memory``: a fresh server's peak RSS (``VmHWM``) after one ``POST /v1/register`` uploading both clouds as float32
  ``.npy`` files (``general`` only, ``MFGNET_THREADS`` 1), and after two such requests (two pairs) at once with the
  Kubernetes manifest's settings (every bundled model, ``MFGNET_THREADS`` 1, ``MFGNET_MAX_CONCURRENCY`` 2).
- ``parse``: upload + parse of one seeded 2,000,000-point cloud as float32 ``.npy``, binary PLY, ASCII PLY and LAZ:
  the file is the source beside a 31-point target, which the server refuses (422) once both files are decoded. Best
  of two rounds, the files taking turns; and ``plyfile`` reading the same ASCII PLY in this process (what the
  service read ASCII PLY with before its own reader).
"""

from __future__ import annotations

import argparse
import io
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import httpx
import numpy as np

from bench.http_latency import Server, rss_mb
from bench.report_io import emit_report, json_destination, machine_info, positive_int

POINTS = 2_000_000  # MFGNET_MAX_FILE_POINTS' default
MANIFEST_THREADS, MANIFEST_CONCURRENCY = 1, 2  # deploy/k8s/deployment.yaml
PAIRS = ((0, 25.0), (1, 65.0))  # (seed, degrees about z) of the memory part's requests
PARSE_FORMATS = ("npy", "ply-binary", "ply-ascii", "laz")


def full_resolution_pair(seed: int, degrees: float, points: int = POINTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``source [points, 3]``, ``target [points, 3]`` (float32) and the true ``src_to_tgt`` rotation ``[3, 3]``: the
    target turned ``degrees`` about z, -10 about y and 5 about x, and shifted by (0.2, -0.1, 0.05)."""
    from scipy.spatial.transform import Rotation

    from model.analytic_shapes import asymmetric_blob

    rotation = Rotation.from_euler("zyx", [degrees, -10.0, 5.0], degrees=True).as_matrix()
    source = asymmetric_blob(points, 2 * seed)  # [points, 3] independent samples of one surface
    target = asymmetric_blob(points, 2 * seed + 1) @ rotation.T + [0.2, -0.1, 0.05]
    return source.astype(np.float32), target.astype(np.float32), rotation


def rotation_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    """The angle of ``estimate.T @ truth``, in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(np.asarray(estimate).T @ truth) - 1) / 2, -1, 1))))


def in_process_run(repeats: int, points: int) -> dict:
    """In this (fresh) process: ``repeats`` + 1 default registrations of the pair; the first is left out."""
    from service.in_process import LocalRegistrar

    source, target, rotation = full_resolution_pair(*PAIRS[0], points)
    registrar = LocalRegistrar("general")
    seconds, result = [], None
    for _ in range(repeats + 1):
        started = time.perf_counter()
        result = registrar.register(source, target)
        seconds.append(time.perf_counter() - started)
    return {
        "seconds": [round(s, 3) for s in seconds[1:]],
        "first_seconds": round(seconds[0], 3),
        "rotation_error_deg": round(rotation_error_deg(result.transform[:3, :3], rotation), 4),
        "reliable": bool(result.reliable),
        "searched": "search" in result.timing_ms,
    }


def npy_bytes(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points.astype(np.float32))
    return buffer.getvalue()


def upload_pair(url: str, seed: int, degrees: float, points: int) -> float:
    """``POST /v1/register`` of the pair as two ``.npy`` files, no option; its rotation error in degrees."""
    source, target, rotation = full_resolution_pair(seed, degrees, points)
    files = {"source": ("source.npy", npy_bytes(source)), "target": ("target.npy", npy_bytes(target))}
    del source, target
    with httpx.Client(base_url=url, timeout=600) as client:
        response = client.post("/v1/register", files=files)
    if response.status_code != 200:
        raise RuntimeError(f"HTTP {response.status_code}: {response.text[:300]}")
    return round(rotation_error_deg(np.array(response.json()["rotation"]), rotation), 4)


def memory_run(points: int) -> dict:
    """Peak RSS in MiB of a fresh one-model server after one pair, and of a fresh manifest-like server after two at
    once."""
    with Server(threads=1, models="general") as server:
        errors = [upload_pair(server.url, *PAIRS[0], points)]
        one = rss_mb(server.proc.pid, "VmHWM")
    with Server(threads=MANIFEST_THREADS, max_concurrency=MANIFEST_CONCURRENCY) as server:
        with ThreadPoolExecutor(len(PAIRS)) as pool:
            errors += list(pool.map(lambda pair: upload_pair(server.url, *pair, points), PAIRS))
        two = rss_mb(server.proc.pid, "VmHWM")
    return {"one_request_one_model_mib": round(one, 1), "two_requests_manifest_mib": round(two, 1),
            "rotation_errors_deg": errors}


def parse_files(folder: Path, points: int) -> dict[str, Path]:
    """One seeded ``points``-point float32 cloud written in each of :data:`PARSE_FORMATS`, and the 31-point target."""
    import laspy

    from service.pointcloud_io import write_points

    cloud = np.random.default_rng(0).normal(size=(points, 3)).astype(np.float32)  # [points, 3]
    paths = {name: folder / f"big.{name.split('-')[0]}" for name in PARSE_FORMATS}
    paths["ply-ascii"] = folder / "big_ascii.ply"
    np.save(paths["npy"], cloud)
    write_points(paths["ply-binary"], cloud)
    with open(paths["ply-ascii"], "w") as out:
        out.write(f"ply\nformat ascii 1.0\nelement vertex {points}\nproperty float x\nproperty float y\n"
                  "property float z\nend_header\n")
        np.savetxt(out, cloud, fmt="%.6f")
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [1e-4] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.T.astype(np.float64)
    las.write(paths["laz"], do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
    np.save(folder / "few.npy", cloud[:31])
    return paths


def parse_run(folder: Path, paths: dict[str, Path]) -> dict:
    """Upload + parse seconds per format (best of two rounds) on a fresh default server; ``plyfile``'s read of the
    ASCII PLY in process."""
    import plyfile

    target = (folder / "few.npy").read_bytes()
    seconds: dict[str, float] = {}
    with Server(threads=1, models="general") as server, httpx.Client(base_url=server.url, timeout=600) as client:
        for name in PARSE_FORMATS * 2:
            files = {"source": (paths[name].name, paths[name].read_bytes()), "target": ("few.npy", target)}
            started = time.perf_counter()
            response = client.post("/v1/register", files=files, data={"rotation_search": "false"})
            elapsed = time.perf_counter() - started
            if response.status_code != 422 or "32" not in response.text:
                raise RuntimeError(f"{name}: expected the 31-point target's 422, got HTTP {response.status_code}: "
                                   f"{response.text[:300]}")
            seconds[name] = min(seconds.get(name, np.inf), elapsed)
    started = time.perf_counter()
    plyfile.PlyData.read(str(paths["ply-ascii"]))
    seconds["plyfile_ascii_in_process"] = time.perf_counter() - started
    return {name: round(value, 3) for name, value in seconds.items()}


def measure(runs: int, repeats: int, points: int = POINTS, parts: tuple[str, ...] = ("in_process", "memory", "parse")
            ) -> dict:
    """Every part of ``parts``, ``runs`` times each."""
    report: dict = {"benchmark": "full_resolution", "points": points, "runs": runs, "pairs": [list(p) for p in PAIRS]}
    if "in_process" in parts:
        report["repeats"] = repeats
        report["in_process"] = []
        for _ in range(runs):  # one fresh process per run: its first call pays for allocations
            with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
                report["in_process"].append(pool.submit(in_process_run, repeats, points).result())
    if "memory" in parts:
        report["memory"] = [memory_run(points) for _ in range(runs)]
    if "parse" in parts:
        with tempfile.TemporaryDirectory(prefix="mfgnet-full-resolution-") as folder:
            paths = parse_files(Path(folder), points)
            report["upload_mib"] = {name: round(path.stat().st_size / 2**20, 1) for name, path in paths.items()}
            report["parse_seconds"] = [parse_run(Path(folder), paths) for _ in range(runs)]
    from service.registrar import default_threads

    report["threads"] = {"in_process": default_threads(), "servers": 1}
    report["machine"] = machine_info(default_threads())
    return report


def cloud_points(text: str) -> int:
    """``--points``: a whole number from 1,000 (the parse part's target has 31) to :data:`POINTS` (the limit)."""
    value = int(text)  # a ValueError is argparse's "invalid cloud_points value"
    if not 1_000 <= value <= POINTS:
        raise argparse.ArgumentTypeError(f"must be from 1000 to {POINTS} (the file uploads' limit), got {value}")
    return value


def parts_list(text: str) -> tuple[str, ...]:
    """``--parts``' comma-separated names, each one of ``in_process``, ``memory``, ``parse``."""
    known = ("in_process", "memory", "parse")
    names = tuple(dict.fromkeys(name.strip() for name in text.split(",") if name.strip()))
    if not names or any(name not in known for name in names):
        raise argparse.ArgumentTypeError(f"expected parts among {', '.join(known)}, got {text!r}")
    return names


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=positive_int, default=3, help="times each part runs (fresh processes)")
    parser.add_argument("--repeats", type=positive_int, default=3,
                        help="timed in-process registrations per run, after a first one left out")
    parser.add_argument("--points", type=cloud_points, default=POINTS, help="points per cloud")
    parser.add_argument("--parts", type=parts_list, default=("in_process", "memory", "parse"),
                        help="comma separated, of in_process, memory, parse (default: all)")
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args(argv)
    json_destination(args.json)
    report = measure(args.runs, args.repeats, args.points, args.parts)
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
