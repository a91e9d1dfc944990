"""Turntable range scans of objects other than the dragon: ``python -m bench.turntable_scans``.

The real-scan set's range images are all of one object (the Stanford dragon). This benchmark scans other objects the
same way, with :func:`model.sensor_sim.scan`: each shape is centred and scaled to a radius of ``RADIUS`` (0.1 m, an
object about 0.2 m across, as the dragon), stands on a turntable turning about its up axis (z, as ModelNet40's tall
classes stand) and is seen by one fixed range camera ``CAMERA_DISTANCE`` from its centre, ``ELEVATION_DEG`` above the
table, at 0 deg and at each of ``--angles`` (default 24 and 48 deg, as the dragon's pairs). The camera returns one
point per pixel of ``PIXEL_PITCH`` (:func:`model.sensor_sim.pixel_grid_returns`): about 0.7 mm apart on the object,
0.0035 of its size, as the dragon's images are 0.54 mm apart on a dragon 0.15 m across
(``docs/decisions/0095-turntable-scans-on-a-pixel-grid.md``). Each scan at an angle is
paired with the scan at 0 deg (``<shape>_<angle>_0``, sensor ``cyberware-range``: right within 5 deg and 1 cm, the data
README's thresholds), and every pair is registered as scanned and at ``--turns`` seeded Haar-uniform rotations of the
source for each of ``--seeds`` (:func:`bench.real_scans.pair_cases`; the as-scanned cases once).

Shapes (``--shapes``): ModelNet40 test shapes of the named classes (the first ``--count`` of each in the test file,
1,024 points densified to a surface of 204,800 before the scans; ``$MFGNET_DATA`` or ``--data``) and the analytic
round shapes of :mod:`model.analytic_shapes` (``lumpy_sphere``, ``bumpy_ellipsoid``, ``asymmetric_blob``,
``smooth_blob``: closed surfaces of 200,000 points without symmetries). Each is put in one of three kinds:
``solids of revolution`` (bottle, vase, lamp, cup, flower_pot: a turn about their own axis changes little),
``other shapes`` (the other ModelNet40 classes) and ``analytic round``. The scans are seeded by the shape's name: a
shape gets the same scans whichever others are loaded (its turned cases depend on which are, as the real set's do).

Every case is registered in process (:class:`service.registrar.Registrar`) with the service's request defaults
(:data:`bench.search_network.DEFAULTS`), by the bundled ``general`` model or ``--model-dir``'s; each wrong result is
classed as :mod:`bench.failures` classes it (``truth leaves``, ``fits worse``, ``not reached``: registered again from
the true pose). Open3D FPFH + RANSAC + ICP registers the same clouds (:func:`bench.real_scans.run_fpfh`, seeded by the
first seed; ``--no-fpfh`` skips it). In process, so there is no ``--compare-root``: run the command in each checkout
and compare the reports.

It prints one line per case (:func:`bench.real_scans.print_table`) and a table per kind and per class (cases, the
service's and FPFH's successes, ``reliable`` given and wrong, seconds, failures per class); ``--json`` writes it all
with what made it (:func:`bench.report_io.provenance`)::

    python -m bench.turntable_scans                            # 10 ModelNet40 classes x 2 shapes and 4 analytic
    python -m bench.turntable_scans --shapes cup lumpy_sphere --count 1 --turns 1 --no-fpfh
    python -m bench.turntable_scans --model-dir model/exported/candidate --no-fpfh --json /tmp/candidate.json
"""

from __future__ import annotations

import argparse
import json
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench.baselines import refuse_fpfh_without_open3d
from bench.failures import CLASSES, failure_row
from bench.real_scans import (
    THRESHOLDS,
    Case,
    case_thresholds,
    judged,
    pair_cases,
    print_table,
    run_fpfh,
    summarise,
)
from bench.report_io import (
    checked,
    json_destination,
    machine_info,
    non_negative_int,
    positive_float,
    positive_int,
    provenance,
)
from bench.scan_pairs import ScanPair
from bench.search_network import registered
from model.analytic_shapes import asymmetric_blob, bumpy_ellipsoid, lumpy_sphere, smooth_blob
from model.sensor_pairs import UP
from model.sensor_sim import SensorEffects, densify, estimate_normals, scan
from service.manifest import bundled_models_dir
from service.registrar import Registrar, default_threads

SENSOR = "cyberware-range"  # judged by the data README's range-image thresholds (5 deg, 1 cm)
RADIUS = 0.1  # metres from the shape's centre to its farthest point: an object about 0.2 m across, as the dragon
CAMERA_DISTANCE = 3.5 * RADIUS  # from the turntable's axis to the camera
ELEVATION_DEG = 15.0  # the camera's height above the table's plane through the shape's centre, as an angle
PIXEL_PITCH = 0.002  # radians: the camera's pixel, about 0.7 mm on the object from 0.35 m
# a laser range scanner's noise (0.05% of the range) and its flying pixels, on its pixel grid
EFFECTS = SensorEffects(relative_noise=0.0005, mixed_share=0.01, pixel_pitch=PIXEL_PITCH)
MODELNET_DENSIFY = 200  # 1,024-point ModelNet40 shapes -> 204,800 points on their surface before the scans
ANALYTIC = {
    "lumpy_sphere": lumpy_sphere,
    "bumpy_ellipsoid": bumpy_ellipsoid,
    "asymmetric_blob": asymmetric_blob,
    "smooth_blob": smooth_blob,
}
ANALYTIC_POINTS, ANALYTIC_SEED = 200_000, 7
REVOLUTION = ("vase", "cup", "lamp", "bottle", "flower_pot")  # solids of revolution about the up axis, or nearly
DEFAULT_SHAPES = ("person", "plant", "toilet", "chair", "car", *REVOLUTION, *ANALYTIC)
KINDS = ("other shapes", "solids of revolution", "analytic round")
SCAN_SEED = 0  # with the shape's name, seeds its surface sample and its scans


@dataclass(frozen=True)
class Shape:
    """A dense surface sample to scan: ``points [N, 3]``, unit ``normals [N, 3]`` (unoriented), in its own unit."""

    name: str  # a ModelNet40 file name (person_0089) or an analytic shape's name
    group: str  # its ModelNet40 class, or for an analytic shape its name
    points: np.ndarray
    normals: np.ndarray

    @property
    def kind(self) -> str:
        if self.group in ANALYTIC:
            return "analytic round"
        return "solids of revolution" if self.group in REVOLUTION else "other shapes"


def shape_rng(name: str) -> np.random.Generator:
    """The generator of one shape's surface sample and scans: the same whichever other shapes are loaded."""
    return np.random.default_rng([SCAN_SEED, zlib.crc32(name.encode())])


def modelnet_shapes(classes: list[str], count: int, data: str | None = None) -> list[Shape]:
    """The first ``count`` ModelNet40 test shapes of each of ``classes`` (in the test file's order), densified."""
    from model.data import class_names, load_shapes, shapes_file

    if not classes:
        return []
    points, labels = load_shapes("test", "clean", data)  # [S, 1024, 3], [S]
    names = class_names(data)
    with np.load(shapes_file("test", "clean", data), allow_pickle=False) as archive:
        file_names = archive["names"] if "names" in archive.files else None
    shapes = []
    for group in classes:
        for index in np.flatnonzero(labels == names.index(group))[:count]:
            name = str(file_names[index]) if file_names is not None else f"{group}_{index}"
            sample = points[index].astype(np.float64)
            dense, normals = densify(sample, estimate_normals(sample), MODELNET_DENSIFY, shape_rng(name))
            shapes.append(Shape(name, group, dense, normals))
    return shapes


def analytic_shape(name: str) -> Shape:
    points = np.asarray(ANALYTIC[name](ANALYTIC_POINTS, seed=ANALYTIC_SEED), dtype=np.float64)
    return Shape(name, name, points, estimate_normals(points))


def about_up(degrees: float) -> np.ndarray:
    """``[3, 3]``: a turn of the turntable by ``degrees`` about the up axis."""
    return Rotation.from_euler("xyz"[UP], degrees, degrees=True).as_matrix()


def turntable_pairs(shape: Shape, angles: list[float], effects: SensorEffects | None = None) -> list[ScanPair]:
    """The scan at each of ``angles`` paired with the scan at 0 deg, in metres, each made with ``effects`` (default:
    ``EFFECTS``); ground truth: the turn back."""
    centred = shape.points - shape.points.mean(0)
    points = centred * (RADIUS / np.linalg.norm(centred, axis=1).max())  # [N, 3]
    elevation = np.radians(ELEVATION_DEG)
    camera = np.zeros(3)
    camera[(UP + 1) % 3], camera[UP] = CAMERA_DISTANCE * np.cos(elevation), CAMERA_DISTANCE * np.sin(elevation)
    look = -camera / np.linalg.norm(camera)
    rng = shape_rng(shape.name)
    effects = EFFECTS if effects is None else effects
    views = {}
    for angle in (0.0, *angles):  # the object turned by the table, the camera fixed
        turn = about_up(angle)
        views[angle] = scan(points @ turn.T, shape.normals @ turn.T, camera, look, effects, rng).astype(np.float32)
    pairs = []
    for angle in angles:
        truth = np.eye(4)
        truth[:3, :3] = about_up(-angle)  # scan at ``angle`` -> scan at 0: the table turned back
        pairs.append(ScanPair(f"{shape.name}_{angle:g}_0", SENSOR, views[angle], views[0.0], truth))
    return pairs


def outcome(registrar: Registrar, case: Case) -> dict:
    """One case registered with the defaults: errors, success, ``reliable``, seconds, the stages' time and, for a
    wrong result, its failure class and the run from the true pose (:func:`bench.failures.failure_row`)."""
    result, seconds = registered(registrar, case)
    returned = judged(case, result.rotation, result.translation)
    row = {
        **returned,
        "reliable": bool(result.reliable),
        "seconds": round(seconds, 4),
        "inlier_ratio": round(float(result.inlier_ratio), 4),
        "timing_ms": {key: round(v, 1) for key, v in result.timing_ms.items()},
    }
    if not returned["success"]:
        failed = failure_row(registrar, case, result, returned, seconds)
        row.update(failure=failed["class"], from_truth=failed["from_truth"])
    return row


def figures(cases: list[Case], service: list[dict], fpfh: list[dict] | None) -> dict:
    """The totals of ``cases`` (:func:`bench.real_scans.summarise`), the ``reliable`` results that are wrong, and the
    service's failures per class."""
    counts = Counter(row.get("failure") for row in service if not row["success"])
    entry = summarise(cases, service, fpfh)["x1"]
    return {
        **entry,
        "reliable_wrong": entry["reliable_given"] - entry["reliable_right"],
        "failures": {name: counts[name] for name in CLASSES},
    }


def grouped(cases: list[Case], service: list[dict], fpfh: list[dict] | None, keys: list[str]) -> dict:
    """:func:`figures` per distinct key of ``keys`` (one per case), in first-seen order."""
    out = {}
    for key in dict.fromkeys(keys):
        pick = [i for i, k in enumerate(keys) if k == key]
        out[key] = figures(
            [cases[i] for i in pick], [service[i] for i in pick], [fpfh[i] for i in pick] if fpfh else None
        )
    return out


def print_figures(title: str, table: dict, with_fpfh: bool) -> None:
    print(
        f"\n{title:24} {'cases':>5} {'svc':>4} {'fpfh':>4} {'rel (wrong)':>11} {'svc s':>7} {'fpfh s':>7}  "
        + "  ".join(CLASSES)
    )
    for name, f in table.items():
        ref = (f"{f['fpfh_successes']:>4}", f"{f['fpfh_seconds']:7.1f}") if with_fpfh else (f"{'-':>4}", f"{'-':>7}")
        print(
            f"{name:24} {f['cases']:5} {f['service_successes']:4} {ref[0]} "
            f"{f['reliable_given']:5} ({f['reliable_wrong']:3}) {f['service_seconds']:7.1f} {ref[1]}  "
            + "  ".join(f"{f['failures'][c]:{len(c)}}" for c in CLASSES)
        )


def angle_list(parser: argparse.ArgumentParser, angles: list[float]) -> list[float]:
    """``--angles``, each above 0 and below 360 deg (0 would pair a scan with itself), none twice; else a usage
    error."""
    for angle in angles:
        if not angle < 360:
            parser.error(f"--angles: each turn must be above 0 and below 360 deg, got {angle:g}")
    if len(set(angles)) != len(angles):
        parser.error(f"--angles: an angle given twice in {' '.join(f'{a:g}' for a in angles)}")
    return angles


def chosen_shapes(parser: argparse.ArgumentParser, shapes: list[str], data: str | None) -> list[str]:
    """``--shapes``, each an analytic shape's name or a ModelNet40 class (the data is checked first when one is
    named); else a usage error naming what is there."""
    if len(set(shapes)) != len(shapes):
        parser.error(f"--shapes: a shape given twice in {' '.join(shapes)}")
    classes = [name for name in shapes if name not in ANALYTIC]
    if classes:
        from model.cli_inputs import require_shapes
        from model.data import class_names

        checked(require_shapes, "test", "clean", data)
        known = class_names(data) or []
        unknown = [name for name in classes if name not in known]
        if unknown:
            there = ", ".join(known) or "none: no modelnet40_shape_names.txt"
            parser.error(
                f"--shapes: no analytic shape or ModelNet40 class {', '.join(unknown)} (analytic: "
                f"{', '.join(ANALYTIC)}; classes: {there})"
            )
    return shapes


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--shapes",
        nargs="+",
        default=list(DEFAULT_SHAPES),
        help=f"ModelNet40 classes and analytic shapes ({', '.join(ANALYTIC)}) to scan",
    )
    parser.add_argument("--count", type=positive_int, default=2, help="ModelNet40 shapes per class")
    parser.add_argument(
        "--angles",
        type=positive_float,
        nargs="+",
        default=[24.0, 48.0],
        help="turntable angles (deg) whose scans are paired with the scan at 0 deg",
    )
    parser.add_argument(
        "--seeds",
        type=non_negative_int,
        nargs="+",
        default=[0],
        help="seeds of the turned cases (and the first, of RANSAC)",
    )
    parser.add_argument("--turns", type=positive_int, default=2, help="turned cases per pair and seed")
    parser.add_argument("--model-dir", type=Path, help="exported model to register with (default: bundled general)")
    parser.add_argument("--data", help="ModelNet40 directory (default: $MFGNET_DATA, then ../shared)")
    parser.add_argument("--no-fpfh", action="store_true", help="skip FPFH + RANSAC + ICP (no Open3D needed)")
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)
    shapes = chosen_shapes(parser, args.shapes, args.data)
    angles = angle_list(parser, args.angles)
    json_destination(args.json, create_folders=True)
    if args.model_dir:
        from model.cli_inputs import model_dir

        checked(model_dir, args.model_dir, "--model-dir")
    refuse_fpfh_without_open3d(parser, args)
    model = args.model_dir or bundled_models_dir() / "general"
    made_by = provenance([model])  # before the run: the shared checkout may move on during it
    classes = [name for name in shapes if name not in ANALYTIC]
    scanned = modelnet_shapes(classes, args.count, args.data) + [analytic_shape(n) for n in shapes if n in ANALYTIC]
    pairs, of_pair = [], {}
    for shape in scanned:
        for pair in turntable_pairs(shape, angles):
            pairs.append(pair)
            of_pair[pair.name] = shape
    cases = []
    for i, seed in enumerate(args.seeds):  # the as-scanned cases with the first seed only
        cases += [c for c in pair_cases(pairs, seed, (1.0,), args.turns) if i == 0 or c.variant != "scanned"]
    registrar = Registrar(model)
    registered(registrar, cases[0])  # the first call sets the runtime up, untimed
    service = [outcome(registrar, case) for case in cases]
    fpfh = None if args.no_fpfh else run_fpfh(cases, args.seeds[0])
    print_table(cases, service, fpfh)
    kinds = grouped(cases, service, fpfh, [of_pair[c.name].kind for c in cases])
    groups = grouped(cases, service, fpfh, [of_pair[c.name].group for c in cases])
    everything = figures(cases, service, fpfh)
    print_figures("kind", {**kinds, "all": everything}, fpfh is not None)
    print_figures("class or shape", groups, fpfh is not None)
    degrees, metres = THRESHOLDS[SENSOR]
    print(
        f"\nright: rotation error < {degrees:g} deg and translation error < {100 * metres:g} cm; rel (wrong): "
        "results given reliable: true (of them wrong); seconds summed over the cases"
    )
    rows = [
        {
            "pair": c.name,
            "shape": of_pair[c.name].name,
            "class": of_pair[c.name].group,
            "kind": of_pair[c.name].kind,
            "variant": c.variant,
            "points": [len(c.source), len(c.target)],
            "thresholds": dict(zip(("rotation_deg", "translation"), case_thresholds(c), strict=True)),
            "service": service[i],
            **({"fpfh": fpfh[i]} if fpfh else {}),
        }
        for i, c in enumerate(cases)
    ]
    report = {
        "benchmark": "turntable_scans",
        "shapes": shapes,
        "count": args.count,
        "angles": angles,
        "seeds": args.seeds,
        "turns": args.turns,
        "fpfh": fpfh is not None,
        "scans": {
            "sensor": SENSOR,
            "radius_m": RADIUS,
            "camera_distance_m": CAMERA_DISTANCE,
            "elevation_deg": ELEVATION_DEG,
            "relative_noise": EFFECTS.relative_noise,
            "mixed_share": EFFECTS.mixed_share,
            "pixel_pitch_rad": EFFECTS.pixel_pitch,
            "shapes": {s.name: s.kind for s in scanned},
        },
        "machine": machine_info(default_threads()),
        "provenance": made_by,
        "units": "rotation errors in degrees; translation errors and thresholds in metres; seconds",
        "totals": {"all": everything, "kinds": kinds, "classes": groups},
        "rows": rows,
    }
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return report


if __name__ == "__main__":
    main()
