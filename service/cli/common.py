"""What every runtime ``mfgnet`` command shares: the usage-error exit, reading a cloud, checking an output path."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NoReturn

import numpy as np
import typer

SERVE_EXTRA_HINT = "this command needs the runtime extra: pip install 'mfgnet[serve]'"
UNRELIABLE_EXIT = 3  # --require-reliable: registered, but quality.reliable is false


def fail(message: str, code: int = 2) -> NoReturn:
    """Print ``message`` on stderr and exit with ``code`` (2: bad input or usage, 1: anything else)."""
    typer.echo(f"mfgnet: error: {message}", err=True)
    raise typer.Exit(code=code)


def check_output_path(path: Path | None, option: str) -> None:
    """A usage error where the output ``path`` of ``option`` is a folder or lies in a folder that does not exist."""
    if path is not None and path.is_dir():
        fail(f"{option} {path}: a folder, not a file")
    if path is not None and not path.parent.is_dir():
        fail(f"{option} {path}: folder {path.parent} does not exist")


def same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file: the same inode where both exist (hard links, symbolic links, case-folding
    file systems), else the same resolved path."""
    if a.exists() and b.exists():
        return os.path.samefile(a, b)
    return a.resolve() == b.resolve()


def require_regular_file(path: Path) -> None:
    """A usage error where ``path`` is a FIFO, a device or a socket: its ``open()`` could block for ever."""
    if path.exists() and not path.is_file() and not path.is_dir():
        fail(f"cannot read {path}: not a regular file")


def read_cloud(path: Path, name: str | None = None) -> np.ndarray:
    """``[N, 3]`` float64 points of ``path`` (any format :mod:`service.pointcloud_io` reads), or a usage error
    (prefixed with ``name``, e.g. ``frame 3 a.ply``, where given)."""
    from service.pointcloud_io import PointCloudFormatError, read_points

    require_regular_file(path)
    try:
        return read_points(path).astype(np.float64)
    except PointCloudFormatError as exc:
        fail(f"{name}: {exc}" if name else str(exc))
    except OSError as exc:
        reason = exc.strerror or exc
        fail(f"{name}: cannot read it: {reason}" if name else f"cannot read {path}: {reason}")


def write_text(path: Path, text: str) -> None:
    """``text`` into ``path``, or exit 1 naming why it cannot be written."""
    try:
        path.write_text(text)
    except OSError as exc:
        fail(f"cannot write {path}: {exc.strerror or exc}", code=1)


def write_aligned_cloud(path: Path, source: Path | None, points: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
    """``--write-aligned``: the file ``source`` itself moved by ``R [3, 3]``, ``t [3]`` where ``path``'s extension is
    one of its own format's (PLY, PCD, LAS/LAZ, XYZ/CSV/TXT, PTS, PTX, NPY, NPZ, E57: :mod:`service.formats.moved`),
    else the x, y, z of ``points [N, 3]`` (read from it) moved, with a note on stderr naming the fields its header
    declares that were left behind; exit 1 where it cannot be written."""
    from service.formats.moved import KEPT_FORMATS, keeps_content, other_fields, source_format, write_moved
    from service.pointcloud_io import PointCloudFormatError, write_points

    moved = points @ R.T + t  # [N, 3]
    kind = source_format(source) if source is not None else None
    kept = keeps_content(kind, path)
    try:
        if kept:
            write_moved(source, path, R, t, largest=float(np.abs(moved).max()))
        else:
            write_points(path, moved)
    except (PointCloudFormatError, OSError) as exc:
        fail(f"cannot write {path}: {exc}", code=1)
    typer.echo(f"wrote {path}", err=True)
    dropped = [] if kept else other_fields(source, kind)
    if dropped:
        shown = ", ".join(dropped[:6]) + (", ..." if len(dropped) > 6 else "")
        typer.echo(
            f"mfgnet: note: {path.name} holds x, y, z only; {source.name}'s other fields ({shown}) are kept in a "
            f"{'/'.join(KEPT_FORMATS[kind])} output",
            err=True,
        )


def check_aligned_source(source: Path, out_name: str) -> None:
    """Exit 2 where ``source``, written as ``out_name`` in its own format (:func:`service.formats.moved.keeps_content`),
    cannot be written moved as far as its header decides (:func:`service.formats.moved.check_moved`: an E57 file
    whose XML section cannot be rewritten, an ``.npy`` or ``.npz`` array the writer refuses, an 8-byte integer array's
    values beyond 2**53 among them), before any registration runs. A source the reader refuses passes here
    (:func:`~service.formats.moved.check_moved` leaves it to the reader): reading it names what is wrong, as for every
    other format."""
    from service.formats.moved import FORMAT_NAMES, check_moved, keeps_content, source_format
    from service.pointcloud_io import PointCloudFormatError

    kind = source_format(source)
    if not keeps_content(kind, out_name):
        return
    try:
        check_moved(source, kind)
    except PointCloudFormatError as exc:
        fail(f"--write-aligned {out_name}: {source.name} cannot be written moved as {FORMAT_NAMES[kind]}: {exc}")
    except OSError:
        return  # reading it says why


def number(value: float | None, spec: str = ".4g") -> str:
    """``value`` formatted for a summary line, ``?`` where it is missing."""
    return "?" if value is None else format(float(value), spec)
