"""What made a training run or a benchmark report: this checkout's commit, the data file read, the command line and
the library versions.

``mfgnet train`` records :func:`run_record` in its checkpoints and ``config.json`` (``mfgnet export`` carries it into
the manifest's ``training``); the benchmarks' reports record :func:`checkout` (``bench.report_io.provenance``).
Standard library and numpy only: ``bench`` imports it where torch may be absent.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent  # the checkout (or the installed packages' folder)


def checkout(root: Path = ROOT) -> dict:
    """``commit``: the HEAD of the git checkout whose top folder is ``root`` (``None`` where ``root`` is no checkout's
    top: an installed package, even in a virtual environment inside a checkout; a container), and
    ``uncommitted_changes``: whether files git tracks differ from that commit (``None`` without a commit)."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30).stdout

    try:
        found = git("rev-parse", "--show-toplevel", "HEAD").splitlines()  # [top folder, commit]
        commit = found[1] if len(found) == 2 and Path(found[0]).resolve() == Path(root).resolve() else None
        changed = git("status", "--porcelain", "--untracked-files=no").strip() != "" if commit else None
    except (OSError, subprocess.SubprocessError):  # no git here
        commit, changed = None, None
    return {"commit": commit, "uncommitted_changes": changed}


def portable_path(path: str | os.PathLike) -> str:
    """``path`` as a record that means the same on another machine and says nothing of this one's layout: relative
    to the working directory where it lies inside it (``data/modelnet40``), else its last component only (a
    label: ``/home/alice/data/modelnet40`` is ``modelnet40``). What identifies a file is its sha256, beside it."""
    path, here = Path(path).resolve(), Path.cwd().resolve()
    return path.relative_to(here).as_posix() if path.is_relative_to(here) and path != here else path.name


def data_file(path: str | os.PathLike) -> dict:
    """The data file a run reads, to tell it from another copy or version: its folder (:func:`portable_path`: no
    absolute path), name, size in bytes and sha256 (one more read of a file that training loads whole anyway)."""
    from service.manifest import sha256_file

    path = Path(path).resolve()
    return {
        "folder": portable_path(path.parent),
        "file": path.name,
        "bytes": path.stat().st_size,
        "sha256": sha256_file(path),
    }


def versions() -> dict:
    """Python's, numpy's and (where it is installed) torch's versions."""
    import numpy

    found = {"python": platform.python_version(), "numpy": str(numpy.__version__), "torch": None}
    try:
        import torch

        found["torch"] = str(torch.__version__)  # a str subclass that weights_only loading refuses
    except ImportError:
        pass
    return found


def run_record(options: dict, data: str | os.PathLike, **extra) -> dict:
    """What starts (or resumes) a training run here: :func:`checkout`, the :func:`data_file` ``data``, this process's
    command line, the run's ``options``, :func:`versions` and the time (UTC), with ``extra`` entries."""
    return {
        **checkout(),
        "data": data_file(data),
        "command": list(sys.argv),
        "options": options,
        "versions": versions(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **extra,
    }
