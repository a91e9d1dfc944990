"""Real-scan benchmark: the service as a user calls it, beside FPFH + RANSAC + ICP, in one run.

Every pair of the real-scan set (``$MFGNET_REAL_DATA``, else ``../shared/data/real``) goes to a real server on
127.0.0.1 as two ``.npy`` uploads with no option, as scanned and with the source turned by a seeded
Haar-uniform rotation, in metres and again scaled x1000 (millimetres, thresholds scaled). Open3D FPFH + RANSAC +
ICP (the data README's parameters, seeded; the ``bench`` extra; its import not timed) registers the same
clouds in the same run::

    python -m bench.real_scans                      # the whole set; a per-pair table and the totals
    python -m bench.real_scans --json results/general-0.2.0/real_scans.json
    python -m bench.real_scans --pairs dragon_24_0 --no-fpfh --scales 1
    python -m bench.real_scans --turns 4 --no-fpfh     # each pair also at 3 more seeded rotations
    python -m bench.real_scans --derived             # scans the set does not pair (bench.scan_pairs)
    python -m bench.real_scans --densify 300000      # fused fragments at full-resolution size (bench.surface_resample)
    python -m bench.real_scans --no-fpfh --scales 1 --options '{"rotation_search": false}'   # an alternative
    python -m bench.real_scans --no-fpfh --compare-root /tmp/before   # beside another checkout, taking turns
    python -m bench.real_scans --no-fpfh --offset 1000 -2000 500   # both clouds 2 km from their frames' origin
    python -m bench.real_scans --start-near-truth 10 --options '{"rotation_search": false}'   # the speed bound
    python -m bench.real_scans my_pairs --scales 1 --thresholds vlp16=5,0.5   # your own pairs (bench.make_pair)

Success follows the thresholds per sensor class (``docs/REAL_SCANS.md``); ``--thresholds SENSOR=DEG,DIST`` (DIST
in the pair files' unit, scaled with ``--scales``), else a pair file's own ``rotation_threshold_deg`` and
``translation_threshold``, come before them, and a set with a sensor of none is refused before any registration.
A folder of a user's own pairs (``python -m bench.make_pair``) is read as the set is. ``reliable`` precision is the
share of results given ``reliable: true`` that are right; its coverage the share of the service's successes given it.
``--compare-root`` also serves another checkout (its code and its bundled models); the two servers take turns case
by case, so that a machine whose speed drifts between runs weighs on both alike, and the report adds that
checkout's totals and this checkout's time over its. ``--offset X Y Z`` moves both clouds of every case by that
vector before the upload (float32 rounds them there, as it would a map frame's coordinates); poses are judged in
the clouds' own frames, so a rotation error about a far origin does not count as a translation error.
``--start-near-truth DEG`` sends every request an ``initial_transform``: the true pose after the source is turned
``DEG`` degrees about its centroid (a seeded axis per case), which the service also keeps as a candidate. With the
search off it times what a network right at any orientation would leave to do (sampling, the network from that start,
the refinements, the checks): the bound on the end-to-end time of today's pipeline without the rotation search.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import time
import zlib
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path

import httpx
import numpy as np
from scipy.spatial.transform import Rotation

from bench.baselines import refuse_fpfh_without_open3d
from bench.http_latency import Server
from bench.report_io import (
    checked,
    emit_report,
    json_destination,
    json_object,
    machine_info,
    non_negative_int,
    positive_float,
    provenance,
    require_checkouts,
)
from bench.scan_pairs import THRESHOLD_FIELDS, ScanPair, derived_pairs, positive_thresholds, read_pairs
from bench.surface_resample import FUSED_SENSORS, densified
from service.core.config import Settings

DEFAULT_DIR = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
# Success thresholds per sensor class (rotation deg, translation m), from the data README.
THRESHOLDS = {"cyberware-range": (5.0, 0.01), "lidar": (5.0, 2.0)}
INDOOR_THRESHOLDS = (15.0, 0.3)  # kinect-*, xtion-* fused fragments (3DMatch registration recall)
INDOOR_SENSORS = ("kinect-", "xtion-")  # the prefixes of the indoor class's sensor names
# FPFH + RANSAC + ICP on the pair normalised jointly to the unit sphere (the data README's reference).
FPFH_VOXEL, FPFH_NORMAL_RADIUS, FPFH_FEATURE_RADIUS = 0.03, 0.1, 0.25
RANSAC_DISTANCE, RANSAC_EDGE, RANSAC_ITERATIONS, RANSAC_CONFIDENCE = 0.05, 0.9, 100_000, 0.999
ICP_VOXEL, ICP_DISTANCE = 0.01, 0.02
MAX_FILE_POINTS = Settings.model_fields["max_file_points"].default  # what a default server takes per uploaded cloud


def data_dir(path: str | None = None) -> Path:
    """The real-scan set: ``path``, else ``$MFGNET_REAL_DATA``, else ``../shared/data/real`` beside the repo."""
    return Path(path or os.environ.get("MFGNET_REAL_DATA") or DEFAULT_DIR)


def scan_set(parser: argparse.ArgumentParser, path: str | Path | None, names: list[str] | None = None,
             derived: bool = False, option: str = "--pairs") -> Path:
    """The real-scan set :func:`data_dir` finds, checked before any work: a folder of ``*.npz`` pairs holding every pair
    of ``names`` (file stems, or with ``derived`` the derived pairs' names), each file the run reads a pair
    (:func:`bench.scan_pairs.read_pair`); else a usage error of ``parser``."""
    directory = data_dir(path)
    if not directory.is_dir():
        parser.error(f"no real-scan set at {directory} (set MFGNET_REAL_DATA or pass DIR)")
    if not any(directory.glob("*.npz")):
        parser.error(f"no real-scan set at {directory}: no *.npz pairs there (set MFGNET_REAL_DATA or pass DIR)")
    try:  # every file the run reads (derived pairs: all of them), checked as a pair
        read_pairs(directory, None if derived else names)
    except ValueError as err:
        parser.error(str(err))
    if names:
        known = {p.name for p in derived_pairs(directory)} if derived else {f.stem for f in directory.glob("*.npz")}
        unknown = [name for name in names if name not in known]
        if unknown:
            parser.error(f"{option}: no {'derived ' if derived else ''}pair {', '.join(unknown)} in {directory} "
                         f"(there: {', '.join(sorted(known))})")
    return directory


@dataclass(frozen=True)
class Case:
    """One registration to run: a pair in one variant (as scanned or turned) and one unit."""

    name: str
    sensor: str
    variant: str  # "scanned", "turned", "turned-2", ... (load_cases' turns)
    scale: float  # 1: metres, 1000: millimetres
    source: np.ndarray  # [N, 3] float32
    target: np.ndarray  # [M, 3] float32
    src_to_tgt: np.ndarray  # [4, 4] ground truth, in the clouds' own frames
    offset: np.ndarray | None = None  # [3] both clouds moved by it (moved_away); poses are judged without it
    limits: tuple[float, float] | None = None  # its own success thresholds (deg, the case's unit), else its sensor's


def thresholds(sensor: str, scale: float = 1.0) -> tuple[float, float]:
    """Success thresholds (rotation deg, translation in the clouds' unit) of a sensor's class (the data README's:
    ``cyberware-range``, ``kinect-*`` and ``xtion-*``, ``lidar``); ``ValueError`` for a sensor of no class, whose
    results no threshold of the README judges."""
    if sensor in THRESHOLDS:
        degrees, metres = THRESHOLDS[sensor]
    elif sensor.startswith(INDOOR_SENSORS):
        degrees, metres = INDOOR_THRESHOLDS
    else:
        raise ValueError(f"sensor {sensor!r} is of no class with success thresholds (cyberware-range, kinect-*, "
                         "xtion-*, lidar: the data README's)")
    return degrees, metres * scale


def case_thresholds(case: Case) -> tuple[float, float]:
    """The success thresholds (rotation deg, translation in the case's unit) that judge ``case``: its own
    (``--thresholds`` or its pair file's, :func:`load_cases`), else its sensor class's (:func:`thresholds`)."""
    return case.limits if case.limits is not None else thresholds(case.sensor, case.scale)


def require_thresholds(parser: argparse.ArgumentParser, cases: list[Case], option: str | None = None) -> None:
    """A usage error of ``parser`` unless every case of ``cases`` has success thresholds (:func:`case_thresholds`):
    checked before any registration, since :func:`judged` refuses the first result of a sensor of no class. The error
    names the pair-file fields that give thresholds, and ``option`` (``--thresholds``) where the command takes it."""
    for sensor in sorted({case.sensor for case in cases if case.limits is None}):
        try:
            thresholds(sensor)
        except ValueError as error:  # a new set's sensors named otherwise
            fields = f"{' and '.join(THRESHOLD_FIELDS)} in its pair files"
            hint = f"{option} '{sensor}=DEG,DIST' or {fields}" if option else fields
            parser.error(f"{error}; give them with {hint}")


def sensor_threshold(text: str) -> tuple[str, tuple[float, float]]:
    """An argparse ``type`` for ``--thresholds SENSOR=DEG,DIST``: a sensor name, and its success thresholds (rotation
    in degrees, translation in the pair files' unit), both positive."""
    sensor, equals, values = text.rpartition("=")
    if not equals or not sensor or len(values.split(",")) != 2:
        raise argparse.ArgumentTypeError(f"{text!r}: expected SENSOR=DEG,DIST (e.g. lidar=5,2)")
    degrees, distance = positive_thresholds(values, text, "lidar=5,2")
    return sensor, (degrees, distance)


def given_thresholds(parser: argparse.ArgumentParser, given: list[tuple[str, tuple[float, float]]] | None
                     ) -> dict[str, tuple[float, float]]:
    """``--thresholds``' pairs as ``{sensor: (deg, distance)}``; a usage error for a sensor given twice."""
    chosen: dict[str, tuple[float, float]] = {}
    for sensor, limits in given or []:
        if sensor in chosen:
            parser.error(f"--thresholds: sensor {sensor!r} given twice")
        chosen[sensor] = limits
    return chosen


def require_threshold_sensors(parser: argparse.ArgumentParser, chosen: dict[str, tuple[float, float]],
                              cases: list[Case]) -> None:
    """A usage error where ``--thresholds`` names a sensor that no case has: a misspelt name would leave the pairs it
    meant to their sensor class, or to the refusal."""
    sensors = {case.sensor for case in cases}
    for sensor in chosen:
        if sensor not in sensors:
            parser.error(f"--thresholds {sensor}=...: no pair of the run has sensor {sensor!r} "
                         f"(there: {', '.join(sorted(sensors))})")


def threshold_lines(cases: list[Case]) -> list[str]:
    """One line per sensor and thresholds judging ``cases``, in the files' unit (the case's over its scale)."""
    seen = {}
    for case in cases:
        degrees, distance = case_thresholds(case)
        seen.setdefault((case.sensor, degrees, distance / case.scale), None)
    return [f"success for {sensor}: rotation error < {degrees:g} deg and translation error < {distance:g} "
            "(the files' unit, times the scale)" for sensor, degrees, distance in seen]


def turned(source: np.ndarray, src_to_tgt: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The source turned by ``rotation [3, 3]`` about its centroid, and the ground truth of the turned pair."""
    centre = source.mean(0, dtype=np.float64)  # [3]
    moved = (source - centre) @ rotation.T + centre  # [N, 3]; original = R^T (moved - c) + c
    turned_to_src = np.eye(4)
    turned_to_src[:3, :3], turned_to_src[:3, 3] = rotation.T, centre - rotation.T @ centre
    return moved.astype(np.float32), src_to_tgt @ turned_to_src


def load_cases(directory: Path, seed: int = 0, scales: tuple[float, ...] = (1.0, 1000.0),
               names: list[str] | None = None, turns: int = 1, derived: bool = False,
               densify: int | None = None, sensor_thresholds: dict[str, tuple[float, float]] | None = None
               ) -> list[Case]:
    """Every pair of ``directory`` (or only ``names``) as scanned and turned by ``turns`` seeded Haar-uniform rotations
    (variants ``turned``, ``turned-2``, ...), per scale; ``derived``: the pairs derived from the set instead of its
    own (:func:`bench.scan_pairs.derived_pairs`: scans no file pairs, ground truth chained through shared scans).
    ``densify``: each cloud of the fused fragments resampled to that many points on its surface (:func:`densified`,
    seeded by ``seed`` and the pair), as full-resolution fragments hold; the other sensors' clouds as they are.
    ``sensor_thresholds``: ``{sensor: (deg, distance in the files' unit)}``, the success thresholds of that sensor's
    pairs before a pair file's own (``rotation_threshold_deg``, ``translation_threshold``) and its sensor class's;
    the distance is scaled with each case (``Case.limits``).

    The rotations are drawn pair after pair from ``seed``: a pair's ``turned`` is the same whatever ``turns`` is, but
    ``turned-2`` onwards depend on ``turns``, and every rotation on which pairs are loaded (``names``): compare cases
    only between runs that loaded the same pairs with the same ``turns``."""
    pairs = [p for p in derived_pairs(directory) if not names or p.name in names] if derived \
        else read_pairs(directory, names)
    if densify is not None:
        pairs = [densified_pair(pair, densify, seed) for pair in pairs]
    return pair_cases(pairs, seed, scales, turns, sensor_thresholds)


def pair_cases(pairs: list[ScanPair], seed: int = 0, scales: tuple[float, ...] = (1.0, 1000.0), turns: int = 1,
               sensor_thresholds: dict[str, tuple[float, float]] | None = None) -> list[Case]:
    """The cases of ``pairs`` (read from files or made in memory) as :func:`load_cases` describes them: each pair as
    scanned and turned by ``turns`` seeded rotations (drawn pair after pair from ``seed``), per scale."""
    rng, more = np.random.default_rng(seed), np.random.default_rng([seed, 1])  # the first turns, the others
    cases = []
    for pair in pairs:
        rotations = [Rotation.random(random_state=r).as_matrix() for r in [rng] + [more] * (turns - 1)]  # Haar
        variants = {"scanned": (pair.source, pair.src_to_tgt)}
        for k, rotation in enumerate(rotations, start=1):
            variants["turned" if k == 1 else f"turned-{k}"] = turned(pair.source, pair.src_to_tgt, rotation)
        own = (sensor_thresholds or {}).get(pair.sensor, pair.limits)  # (deg, distance in the files' unit) or None
        for scale in scales:
            limits = None if own is None else (own[0], own[1] * scale)
            for variant, (src, T) in variants.items():
                T_scaled = T.copy()
                T_scaled[:3, 3] *= scale
                cases.append(Case(pair.name, pair.sensor, variant, scale, (src * scale).astype(np.float32),
                                  (pair.target * scale).astype(np.float32), T_scaled, limits=limits))
    return cases


def densified_pair(pair: ScanPair, count: int, seed: int) -> ScanPair:
    """``pair`` with each cloud resampled to ``count`` points on its surface where its sensor fused a voxel-reduced
    fragment (:data:`FUSED_SENSORS`; never fewer points than it holds), else ``pair`` itself. Seeded by ``seed`` and the
    pair's name, so a pair gets the same clouds whichever others are loaded."""
    if pair.sensor not in FUSED_SENSORS:
        return pair
    source_rng, target_rng = (np.random.default_rng([seed, 3, zlib.crc32(pair.name.encode()), k]) for k in (0, 1))
    return replace(pair, source=densified(pair.source, max(count, len(pair.source)), source_rng),
                   target=densified(pair.target, max(count, len(pair.target)), target_rng))


def moved_away(cases: list[Case], offset: np.ndarray) -> list[Case]:
    """``cases`` with both clouds moved by ``offset [3]`` (in float64, then rounded to float32 as an upload is); the
    ground truth stays that of the clouds' own frames (:func:`judged` moves a pose back by the offset)."""
    offset = np.asarray(offset, dtype=np.float64)
    return [replace(case, source=(case.source + offset).astype(np.float32),
                    target=(case.target + offset).astype(np.float32), offset=offset) for case in cases]


def pose_errors(rotation: np.ndarray, translation: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Geodesic rotation error (deg) of ``R_pred^T R_true`` and translation error ``||t_pred - t_true||``."""
    # of the nearest rotation: a stored truth 1e-6 off orthonormal (the LiDAR pair's) moves the trace as much as a
    # 0.06 deg error does, and arccos of the raw trace read a 0.051 deg error as 0.000
    relative = np.asarray(rotation, dtype=np.float64).T @ np.asarray(truth, dtype=np.float64)[:3, :3]  # [3, 3]
    degrees = np.degrees(Rotation.from_matrix(relative).magnitude())
    return float(degrees), float(np.linalg.norm(translation - truth[:3, 3]))


def near_truth_starts(cases: list[Case], degrees: float, seed: int) -> list[np.ndarray]:
    """Per case a ``[4, 4]`` ``src_to_tgt`` start ``degrees`` off the truth: the source turned about its centroid by
    that angle (about a seeded uniform axis), then moved by the true pose; its centroid lands where the truth puts it.
    """
    rng = np.random.default_rng([seed, 2])
    starts = []
    for case in cases:
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()  # [3, 3]
        centre = case.source.mean(0, dtype=np.float64)  # [3]
        turn_about_centre = np.eye(4)
        turn_about_centre[:3, :3], turn_about_centre[:3, 3] = turn, centre - turn @ centre
        starts.append(case.src_to_tgt @ turn_about_centre)
    return starts


def npy_bytes(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points.astype(np.float32, copy=False))
    return buffer.getvalue()


def register_http(client: httpx.Client, url: str, source: np.ndarray, target: np.ndarray,
                  options: dict | None = None) -> dict:
    """One ``POST /v1/register`` of two ``.npy`` uploads (and ``options`` as form fields; none by default):
    pose, ``reliable``, client seconds."""
    began = time.perf_counter()
    files = {"source": ("source.npy", npy_bytes(source)), "target": ("target.npy", npy_bytes(target))}
    fields = {key: json.dumps(value) if not isinstance(value, str) else value for key, value in (options or {}).items()}
    response = client.post(url + "/v1/register", files=files, data=fields)
    seconds = time.perf_counter() - began
    if response.status_code != 200:
        return {"status": response.status_code, "error": response.text[:200], "seconds": seconds}
    body = response.json()
    return {"rotation": np.asarray(body["rotation"]), "translation": np.asarray(body["translation"]),
            "reliable": bool(body["quality"]["reliable"]), "warnings": body.get("warnings", []), "seconds": seconds,
            "timing_ms": body.get("timing_ms", {})}


def fpfh_threads() -> int:
    """The threads FPFH + RANSAC + ICP runs on: Open3D's OpenMP default, ``OMP_NUM_THREADS`` where set, else one per
    CPU (the service's own count is a report's ``machine.threads``)."""
    given = os.environ.get("OMP_NUM_THREADS", "").split(",")[0].strip()
    return int(given) if given.isdigit() and int(given) > 0 else os.cpu_count() or 1


def fpfh_ransac_icp(source: np.ndarray, target: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``src_to_tgt`` by Open3D FPFH + RANSAC + point-to-point ICP on the pair normalised to the unit sphere."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    both = np.concatenate([source, target]).astype(np.float64)  # [N + M, 3]
    centre = both.mean(0)
    radius = float(np.linalg.norm(both - centre, axis=1).max())

    def cloud(points: np.ndarray, voxel: float):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector((points.astype(np.float64) - centre) / radius))
        return pcd.voxel_down_sample(voxel)

    def features(pcd: o3d.geometry.PointCloud):
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_NORMAL_RADIUS, max_nn=30))
        return reg.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_FEATURE_RADIUS,
                                                                                     max_nn=100))

    src_c, tgt_c = cloud(source, FPFH_VOXEL), cloud(target, FPFH_VOXEL)
    coarse = reg.registration_ransac_based_on_feature_matching(
        src_c, tgt_c, features(src_c), features(tgt_c), False, RANSAC_DISTANCE,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(RANSAC_EDGE),
         reg.CorrespondenceCheckerBasedOnDistance(RANSAC_DISTANCE)],
        reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE),
    ).transformation
    fine = reg.registration_icp(cloud(source, ICP_VOXEL), cloud(target, ICP_VOXEL), ICP_DISTANCE, coarse,
                                reg.TransformationEstimationPointToPoint(),
                                reg.ICPConvergenceCriteria(max_iteration=30)).transformation
    R_n, t_n = np.asarray(fine)[:3, :3], np.asarray(fine)[:3, 3]
    return R_n, radius * t_n + centre - R_n @ centre  # back to the caller's units


def judged(case: Case, rotation: np.ndarray | None, translation: np.ndarray | None) -> dict:
    """Errors and success of one pose against the case's ground truth (a failed request is a miss)."""
    if rotation is None:
        return {"rotation_error_deg": None, "translation_error": None, "success": False}
    if case.offset is not None:  # y + o = R (x + o) + t  ->  y = R x + t + R o - o
        translation = translation + rotation @ case.offset - case.offset
    r_err, t_err = pose_errors(rotation, translation, case.src_to_tgt)
    max_deg, max_t = case_thresholds(case)
    return {"rotation_error_deg": round(r_err, 3), "translation_error": float(f"{t_err:.4g}"),
            "success": r_err < max_deg and t_err < max_t}


def run_service(cases: list[Case], url: str, options: dict | None = None,
                starts: list[np.ndarray] | None = None) -> list[dict]:
    return run_services(cases, [url], options, starts)[0]


def run_services(cases: list[Case], urls: list[str], options: dict | None = None,
                 starts: list[np.ndarray] | None = None) -> list[list[dict]]:
    """Every case on every server of ``urls``, the servers taking turns (their order flips from case to case): one
    list of rows per server. ``starts``: a ``[4, 4]`` ``initial_transform`` per case, sent with ``options``."""
    rows: list[list[dict]] = [[] for _ in urls]
    with ExitStack() as stack:
        clients = [stack.enter_context(httpx.Client(timeout=300)) for _ in urls]
        for client, url in zip(clients, urls, strict=True):
            register_http(client, url, cases[0].source, cases[0].target, options)  # warm-up, untimed
        for i, case in enumerate(cases):
            sent = options if starts is None else {**(options or {}), "initial_transform": starts[i].tolist()}
            for k in range(len(urls)) if i % 2 == 0 else reversed(range(len(urls))):
                out = register_http(clients[k], urls[k], case.source, case.target, sent)
                row = judged(case, out.get("rotation"), out.get("translation"))
                row.update(seconds=round(out["seconds"], 4), reliable=out.get("reliable"),
                           status=out.get("status", 200), warnings=out.get("warnings", []),
                           **({"error": out["error"]} if "error" in out else {}),
                           timing_ms={key: round(v, 1) for key, v in out.get("timing_ms", {}).items()})
                rows[k].append(row)
    return rows


def run_fpfh(cases: list[Case], seed: int) -> list[dict]:
    import open3d  # noqa: F401  -- imported before timing: its import is not the method's cost

    fpfh_ransac_icp(cases[0].source, cases[0].target, seed)  # first call sets Open3D up, untimed
    rows = []
    for case in cases:
        began = time.perf_counter()
        R, t = fpfh_ransac_icp(case.source, case.target, seed)
        row = judged(case, R, t)
        row["seconds"] = round(time.perf_counter() - began, 4)
        rows.append(row)
    return rows


def summarise(cases: list[Case], service: list[dict], fpfh: list[dict] | None) -> dict:
    """Totals per scale: successes, summed seconds, the speed ratio and the ``reliable`` flag's record."""
    totals = {}
    for scale in sorted({c.scale for c in cases}):
        pick = [i for i, c in enumerate(cases) if c.scale == scale]
        svc = [service[i] for i in pick]
        given = [r for r in svc if r["reliable"]]
        entry = {
            "cases": len(pick),
            "service_successes": sum(r["success"] for r in svc),
            "service_seconds": round(sum(r["seconds"] for r in svc), 3),
            "reliable_given": len(given),
            "reliable_right": sum(r["success"] for r in given),
            "reliable_precision": round(sum(r["success"] for r in given) / len(given), 4) if given else None,
            "reliable_coverage": round(len([r for r in given if r["success"]])
                                       / max(1, sum(r["success"] for r in svc)), 4),
            "stage_seconds": stage_seconds(svc),
        }
        if fpfh is not None:
            ref = [fpfh[i] for i in pick]
            entry.update(fpfh_successes=sum(r["success"] for r in ref),
                         fpfh_seconds=round(sum(r["seconds"] for r in ref), 3))
            entry["speedup"] = round(entry["fpfh_seconds"] / entry["service_seconds"], 3)
            entry.update(precision_where_both_right([cases[i] for i in pick], svc, ref))
        totals[f"x{scale:g}"] = entry
    return totals


def stage_seconds(rows: list[dict]) -> dict[str, float]:
    """The server's own time per stage summed over ``rows`` (each response's ``timing_ms``: ``queue``,
    ``preprocess``, ``encoder``, ``iterations``, ``svd``, ``features``, ``search``, ``refine``, ``postprocess``,
    ``total``), in seconds; where the client's time goes."""
    sums: dict[str, float] = {}
    for row in rows:
        for key, ms in row.get("timing_ms", {}).items():
            if key != "search_per_hypothesis":  # a per-hypothesis share of ``search``, not a stage
                sums[key] = sums.get(key, 0.0) + ms / 1000
    return {key: round(value, 3) for key, value in sums.items()}


def precision_where_both_right(cases: list[Case], service: list[dict], fpfh: list[dict]) -> dict:
    """How precise each method is on the cases both register: median rotation error (deg) and median translation
    error as a share of the case's threshold (the sensors' thresholds differ), per method."""
    both = [i for i in range(len(cases)) if service[i]["success"] and fpfh[i]["success"]]
    entry: dict = {"both_right": len(both)}
    for name, rows in (("service", service), ("fpfh", fpfh)):
        degrees = [rows[i]["rotation_error_deg"] for i in both]
        shares = [rows[i]["translation_error"] / case_thresholds(cases[i])[1] for i in both]
        entry[f"{name}_median_rotation_error_deg"] = round(float(np.median(degrees)), 3) if both else None
        entry[f"{name}_median_translation_share"] = round(float(np.median(shares)), 4) if both else None
    return entry


def print_table(cases: list[Case], service: list[dict], fpfh: list[dict] | None) -> None:
    """One line per case: rotation error (deg), translation error (err_t, in the case's unit: the files' unit times
    the scale, ``x1`` or ``x1000``), success, ``reliable``, client ms; the same for FPFH beside it."""
    head = f"{'pair':22} {'variant':9} {'scale':5} | {'deg':>7} {'err_t':>8} ok rel {'ms':>6}"
    print(head + (f" | {'deg':>7} {'err_t':>8} ok {'ms':>6}" if fpfh else "")
          + "   (deg: rotation error; err_t: translation error in the files' unit times the scale)")
    for i, case in enumerate(cases):
        s = service[i]
        line = (f"{case.name:22} {case.variant:9} {f'x{case.scale:g}':5} | "
                f"{_num(s['rotation_error_deg']):>7} {_num(s['translation_error']):>8} "
                f"{'Y' if s['success'] else '.':2} {'Y' if s['reliable'] else '.':3} {1000 * s['seconds']:6.0f}")
        if fpfh:
            f = fpfh[i]
            line += (f" | {_num(f['rotation_error_deg']):>7} {_num(f['translation_error']):>8} "
                     f"{'Y' if f['success'] else '.':2} {1000 * f['seconds']:6.0f}")
        print(line)


def compared_report(root: Path, cases: list[Case], service: list[dict], compared: list[dict]) -> dict:
    """The other checkout's totals, its rows and, per unit, this checkout's summed time over its."""
    mine, theirs = summarise(cases, service, None), summarise(cases, compared, None)
    return {"root": str(root), "totals": theirs,
            "time_ratio": {scale: round(mine[scale]["service_seconds"] / theirs[scale]["service_seconds"], 3)
                           for scale in mine},
            "pairs": [{"pair": c.name, "variant": c.variant, "scale": c.scale, "service": compared[i]}
                      for i, c in enumerate(cases)]}


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.3g}"


def register_options(text: str) -> dict:
    """An argparse ``type`` for ``--options``: a JSON object of the options ``POST /v1/register`` takes, checked by its
    own schema (an unknown name or a bad value would make every request a 422, measured as failures)."""
    from pydantic import ValidationError

    from service.api.schemas import RegisterOptions

    options = json_object(text, "register options")
    try:
        RegisterOptions.model_validate(options)
    except ValidationError as err:
        first = err.errors()[0]
        raise argparse.ArgumentTypeError(f"{'.'.join(map(str, first['loc']))}: {first['msg']}") from None
    return options


def answering(parser: argparse.ArgumentParser, url: str) -> None:
    """A usage error unless a server at ``url`` says it is ready (``/v2/health/ready``)."""
    try:
        status = httpx.get(url.rstrip("/") + "/v2/health/ready", timeout=10).status_code
    except httpx.HTTPError as err:
        parser.error(f"--url {url}: no server answers ({err})")
    if status != 200:
        parser.error(f"--url {url}: /v2/health/ready answers {status}, not 200")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", nargs="?",
                        help="the real-scan set (default: $MFGNET_REAL_DATA or ../shared/data/real)")
    parser.add_argument("--url", help="an already running server (default: start one on 127.0.0.1)")
    parser.add_argument("--model-dir", type=Path,
                        help="serve only this exported model (its folder name) instead of the bundled default")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the turns and of RANSAC")
    parser.add_argument("--turns", type=int, default=1,
                        help="turned variants per pair (more: figures less tied to one rotation each)")
    parser.add_argument("--scales", type=positive_float, nargs="+", default=[1.0, 1000.0], help="units: 1 m, 1000 mm")
    parser.add_argument("--pairs", nargs="+", help="only these pairs (file stems; the rotations depend on which)")
    parser.add_argument("--derived", action="store_true",
                        help="the pairs derived from the set instead of its own: scans that no file pairs, ground "
                             "truth chained through shared scans (bench.scan_pairs)")
    parser.add_argument("--no-fpfh", action="store_true", help="skip FPFH + RANSAC + ICP (no Open3D needed)")
    parser.add_argument("--thresholds", type=sensor_threshold, action="append", metavar="SENSOR=DEG,DIST",
                        help="success thresholds of SENSOR's pairs: rotation error < DEG degrees and translation error "
                             "< DIST in the pair files' unit (scaled with --scales); before a pair file's own and the "
                             "sensor classes' (repeatable)")
    parser.add_argument("--options", type=register_options, default={},
                        help="register options as JSON, e.g. '{\"rotation_search\": false}' (default: none, as a user)")
    parser.add_argument("--densify", type=int, metavar="POINTS",
                        help="resample each cloud of the fused RGB-D fragments to POINTS points on its surface (the "
                             "size of full-resolution fragments, 260,000-350,000), seeded; other sensors' as they are")
    parser.add_argument("--offset", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="move both clouds of every case by this vector (the clouds' unit) before the upload")
    parser.add_argument("--start-near-truth", type=float, metavar="DEG",
                        help="send each request an initial_transform DEG degrees off the true pose (a seeded axis "
                             "per case): with the search off, the time a network right at any orientation would leave")
    parser.add_argument("--compare-root", type=Path,
                        help="also serve this other checkout (its code and bundled models), taking turns case by case")
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)
    if args.turns < 1:
        parser.error(f"--turns must be at least 1, got {args.turns}")
    if args.compare_root and (args.url or args.model_dir):
        parser.error("--compare-root serves each checkout's own bundled models: not with --url or --model-dir")
    if args.offset and args.start_near_truth is not None:
        parser.error("--start-near-truth starts from the clouds' own frames: not with --offset")
    if args.densify is not None and not 1 <= args.densify <= MAX_FILE_POINTS:
        parser.error(f"--densify must be 1 to {MAX_FILE_POINTS:,} points (the service's file limit): {args.densify}")
    directory = scan_set(parser, args.directory, args.pairs, args.derived)
    json_destination(args.json, create_folders=True)
    require_checkouts(parser, args.compare_root)
    if args.model_dir:
        from model.cli_inputs import model_dir

        checked(model_dir, args.model_dir, "--model-dir")
    chosen = given_thresholds(parser, args.thresholds)
    cases = load_cases(directory, args.seed, tuple(args.scales), args.pairs, args.turns, args.derived, args.densify,
                       chosen)
    if not cases:
        parser.error(f"no {'derived ' if args.derived else ''}pairs to register in {directory}"
                     + (f" named {args.pairs}" if args.pairs else ""))
    require_threshold_sensors(parser, chosen, cases)
    require_thresholds(parser, cases, "--thresholds")
    if args.url:
        answering(parser, args.url)
    refuse_fpfh_without_open3d(parser, args)
    if args.offset:
        cases = moved_away(cases, np.asarray(args.offset))
    starts = None if args.start_near_truth is None else near_truth_starts(cases, args.start_near_truth, args.seed)
    # the model a request naming none gets: --model-dir's, else the default of a server this run starts
    made_by = provenance([] if args.url else [args.model_dir or Settings().default_model])
    compared = None
    if args.url:
        service = run_service(cases, args.url, args.options, starts)
    elif args.compare_root:
        with Server() as server, Server(cwd=str(args.compare_root)) as other:
            service, compared = run_services(cases, [server.url, other.url], args.options, starts)
    else:
        dirs, name = (str(args.model_dir), args.model_dir.name) if args.model_dir else (None, None)
        with Server(model_dirs=dirs, default_model=name) as server:
            service = run_service(cases, server.url, args.options, starts)
    fpfh = None if args.no_fpfh else run_fpfh(cases, args.seed)
    print("\n".join(threshold_lines(cases)))
    print_table(cases, service, fpfh)
    rows = [{"pair": c.name, "sensor": c.sensor, "variant": c.variant, "scale": c.scale,
             "thresholds": dict(zip(("rotation_deg", "translation"), case_thresholds(c), strict=True)),
             "service": service[i], **({"fpfh": fpfh[i]} if fpfh else {})} for i, c in enumerate(cases)]
    report = {"benchmark": "real_scans", "seed": args.seed, "turns": args.turns, "derived": args.derived,
              "densify": args.densify,
              "options": args.options,
              "offset": args.offset,
              "thresholds": {sensor: list(limits) for sensor, limits in chosen.items()},
              "start_near_truth_deg": args.start_near_truth,
              "machine": machine_info(2) | ({"fpfh_threads": fpfh_threads()} if fpfh else {}), "url": args.url,
              "provenance": made_by,
              "units": "rotation errors in degrees; translation errors, offset and a row's translation threshold in "
                       "the case's unit (the pair files' unit times the scale; the set's files are in metres: scale "
                       "1 metres, 1000 millimetres); --thresholds' distances in the files' unit; seconds",
              "totals": summarise(cases, service, fpfh), "pairs": rows}
    printed = {"totals": report["totals"]}
    if compared is not None:
        report["compared"] = compared_report(args.compare_root, cases, service, compared)
        printed["compared"] = {key: report["compared"][key] for key in ("root", "totals", "time_ratio")}
    emit_report(printed, None)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return report


if __name__ == "__main__":
    main()
