"""Another network for the rotation search, judged through the whole pipeline: ``python -m bench.search_network DIR``.

The real-scan set's cases (:func:`bench.real_scans.load_cases`: every pair as scanned and at ``--turns`` seeded
rotations for each of ``--seeds``, in each of ``--scales``; the as-scanned cases once) are registered in process with
the service's defaults (``DEFAULTS``: ``refine="icp-plane"``, ``rotation_search="auto"``) by registrars of the bundled
``general`` model, taking turns case by case: one as it is, and one whose rotation search runs the network of the
exported model ``DIR`` (e.g. a checkpoint of ``mfgnet train --recipe search``, exported with ``mfgnet export --setting
resampled``) through the pipeline's stage hook (:class:`service.stages.pipeline.Stages`); the plain pass, refinements
and checks stay ``general``'s. Every model must normalise clouds as ``general`` does (the same reference radius).
Several ``DIR`` (the checkpoints of one run, say) get one registrar each in the same run, named by their folders, beside
one ``general``.

It prints and writes (``--json``) each registrar's successes (the data README's thresholds), ``reliable`` results
given and wrong, precision, coverage (the share of successes given ``reliable``) and seconds, every case whose
success or ``reliable`` flag differs between them, and what made the report (:func:`bench.report_io.provenance`: the
commit, and ``general`` and each candidate as their manifests name them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

from bench.real_scans import Case, judged, load_cases, require_thresholds, scan_set
from bench.report_io import (
    checked,
    json_destination,
    machine_info,
    non_negative_int,
    positive_float,
    positive_int,
    provenance,
    reliable_totals,
)
from model.cli_inputs import model_dir
from service.manifest import bundled_models_dir
from service.refine_modes import SERVICE_DEFAULT_REFINE
from service.registrar import Registrar, default_threads
from service.result import RegistrationResult
from service.search_mode import SERVICE_DEFAULT_ROTATION_SEARCH
from service.stages.pipeline import Stages
from service.stages.search import search

VARIANTS = ("general", "search network")
DEFAULTS = {"refine": SERVICE_DEFAULT_REFINE, "rotation_search": SERVICE_DEFAULT_ROTATION_SEARCH}  # a request's


def searching_with(network: Registrar) -> Callable:
    """A ``search`` stage that runs ``network``'s graphs instead of the calling registrar's."""

    def search_stage(registrar: Registrar, *args, **kwargs):
        return search(network, *args, **kwargs)

    return search_stage


def variant_names(model_dirs: list[Path]) -> tuple[str, ...]:
    """``general`` and one name per candidate: ``search network`` for one, else each directory's name; ``ValueError``
    for several whose names repeat or are ``general`` (the report's rows are keyed by them)."""
    if len(model_dirs) == 1:
        return VARIANTS
    names = [d.name for d in model_dirs]
    if len(set(names)) != len(names) or "general" in names:
        raise ValueError(f"candidates need distinct folder names other than general, got {names}")
    return ("general", *names)


def normalisation_mismatch(model_dirs: list[Path]) -> str | None:
    """Why a candidate cannot run ``general``'s search (it normalises clouds to another reference radius, read from
    the manifests before any model loads), else ``None``."""
    from service.manifest import load_manifest

    def radius(folder: Path) -> float:  # as Registrar reads it
        return float(load_manifest(folder).normalization.get("reference_radius", 1.0))

    general = radius(bundled_models_dir() / "general")
    for candidate in model_dirs:
        if radius(candidate) != general:
            return (f"{candidate} normalises clouds to a reference radius of {radius(candidate)}, general to "
                    f"{general}: export it with --setting resampled")
    return None


def registrars(model_dirs: list[Path]) -> dict[str, Registrar]:
    """``general`` as bundled, and ``general`` with each candidate's network in its rotation search."""
    names = variant_names(model_dirs)  # before any model loads
    mismatch = normalisation_mismatch(model_dirs)
    if mismatch:
        raise ValueError(mismatch)
    general = bundled_models_dir() / "general"
    plain = Registrar(general)
    swapped = []
    for candidate in model_dirs:
        network = Registrar(candidate)
        swapped.append(Registrar(general, stages=dataclasses.replace(Stages(), search=searching_with(network))))
    return dict(zip(names, (plain, *swapped), strict=True))


def cases(directory: Path, seeds: list[int], turns: int, scales: tuple[float, ...],
          pairs: list[str] | None, derived: bool = False) -> list[Case]:
    """The cases of every seed, the as-scanned ones only with the first; ``derived``: of the pairs derived from the set
    (:func:`bench.scan_pairs.derived_pairs`) instead of its own."""
    out = []
    for i, seed in enumerate(seeds):  # a later seed's turns named apart: "turned@seed1", ... (rows are keyed by it)
        out += [c if i == 0 else dataclasses.replace(c, variant=f"{c.variant}@seed{seed}")
                for c in load_cases(directory, seed, scales, pairs, turns, derived) if i == 0 or c.variant != "scanned"]
    return out


def registered(registrar: Registrar, case: Case) -> tuple[RegistrationResult, float]:
    """One case registered with the service's ``DEFAULTS``: the result and its seconds."""
    started = time.perf_counter()
    result = registrar.register(case.source, case.target, **DEFAULTS)
    return result, time.perf_counter() - started


def outcome(registrar: Registrar, case: Case) -> dict:
    """Success, ``reliable``, errors and seconds of one case."""
    result, seconds = registered(registrar, case)
    return {**judged(case, result.rotation, result.translation), "reliable": bool(result.reliable),
            "seconds": round(seconds, 4)}


def totals(rows: list[dict]) -> dict:
    """Successes, ``reliable`` given / wrong, precision, coverage (:func:`bench.report_io.reliable_totals`) and seconds
    of one variant's ``rows``."""
    return {**reliable_totals(rows), "seconds": round(sum(r["seconds"] for r in rows), 2)}


def compare(model_dirs: list[Path], all_cases: list[Case]) -> dict:
    """Every case through every one of :func:`registrars`, taking turns (the order rotates case by case)."""
    runners = registrars(model_dirs)
    names = tuple(runners)
    rows: dict[str, list[dict]] = {name: [] for name in names}
    for i, case in enumerate(all_cases):
        shift = i % len(names)
        for name in names[shift:] + names[:shift]:
            rows[name].append({"case": f"{case.name}/{case.variant}/x{case.scale:g}", **outcome(runners[name], case)})
    differ = [{"case": same[0]["case"], **{name: {k: row[k] for k in ("success", "reliable", "rotation_error_deg")}
                                          for name, row in zip(names, same, strict=True)}}
              for same in zip(*rows.values(), strict=True)
              if len({(row["success"], row["reliable"]) for row in same}) > 1]
    models = [str(d) for d in model_dirs]
    return {"benchmark": "search_network", "search_model": models[0] if len(models) == 1 else models,
            "totals": {name: totals(r) for name, r in rows.items()}, "differ": differ, "rows": rows}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model_dirs", type=Path, nargs="+", metavar="DIR",
                        help="exported model(s) whose network runs the rotation search; several: all in one run")
    parser.add_argument("--data", type=Path, default=None, help="real-scan set (default: bench.real_scans.data_dir)")
    parser.add_argument("--seeds", type=non_negative_int, nargs="+", default=[0, 1])
    parser.add_argument("--turns", type=positive_int, default=10)
    parser.add_argument("--scales", type=positive_float, nargs="+", default=[1.0, 1000.0])
    parser.add_argument("--pairs", nargs="+", default=None, help="only these pairs (file stems)")
    parser.add_argument("--derived", action="store_true",
                        help="the pairs derived from the set instead of its own "
                             "(the request defaults were not chosen on them)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    directory = scan_set(parser, args.data, args.pairs, args.derived)
    args.model_dirs = [checked(model_dir, folder, "DIR") for folder in args.model_dirs]  # a bundled name: its folder
    try:
        variant_names(args.model_dirs)
    except ValueError as err:
        parser.error(f"DIR: {err}")
    mismatch = normalisation_mismatch(args.model_dirs)
    if mismatch:
        parser.error(f"DIR {mismatch}")
    json_destination(args.json)
    all_cases = cases(directory, args.seeds, args.turns, tuple(args.scales), args.pairs, args.derived)
    require_thresholds(parser, all_cases)  # judged() would refuse a sensor of no class after its first registration
    # general and each candidate, before the run: the shared checkout may move on during it
    made_by = provenance([bundled_models_dir() / "general", *args.model_dirs])
    report = {**compare(args.model_dirs, all_cases), "machine": machine_info(default_threads()), "provenance": made_by}
    for name, figures in report["totals"].items():
        print(name, json.dumps(figures))
    for row in report["differ"]:
        print(json.dumps(row))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
