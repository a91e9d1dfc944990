"""How the ``python -m bench.*`` experiments hand back their report (printed, and saved when asked), and how they
check their command line before any work: a one-line usage error and exit code 2, never a traceback."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def emit_report(report: dict, json_path: Path | None) -> None:
    """Print ``report`` as indented JSON and, with ``json_path``, write the same text there."""
    text = json.dumps(report, indent=2)
    print(text)
    if json_path:
        json_path.write_text(text + "\n")


def checked(check: Callable[..., T], *args, **kwargs) -> T:
    """What ``check`` (one of :mod:`model.cli_inputs`' checks: ``output_file``, ``pairs_file``, ``model_dir``,
    ``require_shapes``...) returns. Its usage error (the message printed on stderr) ends an argparse bench with the
    same exit code 2: the ``typer.Exit`` it raises would end in a traceback outside a typer command."""
    import typer

    try:
        return check(*args, **kwargs)
    except typer.Exit as err:
        raise SystemExit(err.exit_code) from None


def json_destination(path: Path | str | None, create_folders: bool = False) -> Path | None:
    """``--json`` checked before any work (a file that can be written: not a folder, in a writable folder that is
    there, or is made with ``create_folders``), else a usage error."""
    if path is None:
        return None
    from model.cli_inputs import output_file

    return checked(output_file, Path(path), "--json", create_folders)


def npz_arrays(parser: argparse.ArgumentParser, path: Path, keys: tuple[str, ...] = ("source", "target"),
               option: str = "--pairs") -> dict:
    """The arrays ``keys`` of the ``.npz`` file ``path`` (a pairs file needs only its clouds here), else a usage error
    (:mod:`model.cli_inputs`' checks of the file, then of its arrays)."""
    import numpy as np

    from model.cli_inputs import NPZ_FILE_ERRORS, input_file, require_zip, short

    what = f"an .npz of {', '.join(keys)}"
    checked(require_zip, checked(input_file, Path(path), option), option, what)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [key for key in keys if key not in data.files]
            if not missing:
                return {key: data[key] for key in keys}
    except (OSError, *NPZ_FILE_ERRORS) as err:
        parser.error(f"{option} {path}: not {what} ({short(err)})")
    parser.error(f"{option} {path}: not {what} (no {', '.join(missing)})")


def json_object(text: str, what: str) -> dict:
    """For an argparse ``type``: ``text`` as a JSON object, else ``ArgumentTypeError`` naming ``what`` it should
    hold (``register options``, ``MFGNetConfig fields``)."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise argparse.ArgumentTypeError(f"not a JSON object of {what} (not JSON: {err})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"not a JSON object of {what}: {text}")
    return value


def positive_int(text: str) -> int:
    """An argparse ``type``: a whole number of at least 1 (a count of pairs, rounds, turns, requests...)."""
    value = int(text)  # a ValueError is argparse's "invalid positive_int value"
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """An argparse ``type``: a whole number of at least 0 (a seed: NumPy's generators take no negative one)."""
    value = int(text)  # a ValueError is argparse's "invalid non_negative_int value"
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return value


def positive_float(text: str) -> float:
    """An argparse ``type``: a finite number above 0 (a unit scale, a distance...)."""
    value = float(text)  # a ValueError is argparse's "invalid positive_float value"
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def require_checkouts(parser: argparse.ArgumentParser, roots: list[str | Path] | str | Path | None) -> None:
    """A usage error unless every ``--compare-root`` is a folder holding this project's server
    (``service/api/app.py``): another folder would serve this checkout's code from the venv, compared with itself, or
    never start."""
    for root in [roots] if isinstance(roots, (str, Path)) else roots or []:
        if not (Path(root) / "service" / "api" / "app.py").is_file():
            parser.error(f"--compare-root {root}: not a checkout of this project (no service/api/app.py)")


def reliable_totals(rows: list[dict]) -> dict:
    """Cases, successes, ``reliable`` results given and wrong, their precision (the share of those given that are
    right) and coverage (the share of the successes given it) of ``rows`` (each with ``success`` and ``reliable``)."""
    right = sum(r["success"] for r in rows)
    given = sum(r["reliable"] for r in rows)
    wrong = sum(r["reliable"] and not r["success"] for r in rows)
    return {"cases": len(rows), "successes": right, "reliable_given": given, "reliable_wrong": wrong,
            "precision": round((given - wrong) / given, 4) if given else None,
            "coverage": round((given - wrong) / right, 4) if right else None}


def provenance(models: list[str | Path]) -> dict:
    """Which code and models made a report: this checkout's commit (``None`` outside git) and whether files it tracks
    differ from that commit (the report then measured uncommitted code; :func:`model.provenance.checkout`, which
    training runs record too), and each model of ``models`` (bundled name or folder) as its manifest names it:
    ``name``, ``version``, ``folder``."""
    from model.provenance import checkout
    from service.manifest import load_manifest, model_folder

    described = []
    for model in models:
        manifest = load_manifest(model_folder(model))
        described.append({"name": manifest.name, "version": manifest.version, "folder": str(model_folder(model))})
    return {**checkout(), "models": described}


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
