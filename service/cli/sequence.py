"""``mfgnet sequence``: each frame of a sequence registered onto the one before, the model loaded once; JSON lines
and KITTI poses as the steps come."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TextIO

import numpy as np
import typer

from service.cli.common import (
    UNRELIABLE_EXIT,
    check_aligned_source,
    check_output_path,
    fail,
    number,
    read_cloud,
    same_file,
    write_aligned_cloud,
)
from service.cli.model_lookup import load_registrar
from service.cli.options import (
    ApiKeyOpt,
    BusyRetriesOpt,
    DropIsolatedOpt,
    IterationsOpt,
    KeypointsOpt,
    ModelDirs,
    ModelOpt,
    RefineOpt,
    RefinePointsOpt,
    RotationSearchModeOpt,
    RotationSearchOpt,
    ServerOpt,
    ThreadsOpt,
    TimeoutOpt,
    check_server_flags,
    registration_options,
)
from service.cli.records import ServerError, local_record, remote_record, server_client

if TYPE_CHECKING:
    from service.sequence import Step

FramesArg = Annotated[
    list[Path],
    typer.Argument(
        metavar="FRAME",
        show_default=False,
        help="two or more scans in order (.ply .pcd .las .laz .e57 .xyz .txt .csv .pts .ptx .npy .npz); "
        "frame i is registered onto frame i-1",
    ),
]
SequenceOutOpt = Annotated[
    Path | None,
    typer.Option(
        help="write one JSON line per step here ('-': standard output, the default): index, "
        "source, target, the pair's `register --json` record, initial_transform, "
        "accumulated_transform (T_0_i) and accumulated_reliable (false from the first step that is not reliable on)"
    ),
]
KittiOpt = Annotated[
    Path | None,
    typer.Option(
        help="write the accumulated poses T_0_i in the KITTI odometry format: one line per "
        "frame, frame 0's identity first, 12 numbers ([R|t] row-major)"
    ),
]
ConstantVelocityOpt = Annotated[
    bool,
    typer.Option(
        help="pass each step's relative pose as the next step's initial transform (the sensor "
        "keeps moving as it moved; a result far from it carries a warning); without it no guess"
    ),
]
SequenceAlignedOpt = Annotated[
    Path | None,
    typer.Option(
        metavar="DIR",
        help="write every frame moved into frame 0's coordinates (T_0_i) into this folder, named as the frame: "
        "a PLY, PCD, LAS/LAZ, XYZ/CSV/TXT, PTS, PTX, NPY or NPZ frame is that file moved, its other fields kept (as "
        "register --write-aligned); others hold x, y, z; an E57 frame is written as .e57 with its poses "
        "composed",
    ),
]
SequenceReliableOpt = Annotated[
    bool, typer.Option(help="exit 3 when any step is not quality.reliable (every step is still written)")
]


def sequence_command(
    ctx: typer.Context,
    frames: FramesArg,
    out: SequenceOutOpt = None,
    kitti: KittiOpt = None,
    constant_velocity: ConstantVelocityOpt = False,
    write_aligned: SequenceAlignedOpt = None,
    require_reliable: SequenceReliableOpt = False,
    model: ModelOpt = None,
    model_dir: ModelDirs = None,
    iterations: IterationsOpt = None,
    keypoints: KeypointsOpt = None,
    refine: RefineOpt = None,
    refine_points: RefinePointsOpt = None,
    drop_isolated: DropIsolatedOpt = True,
    server: ServerOpt = None,
    api_key: ApiKeyOpt = None,
    timeout: TimeoutOpt = 60.0,
    busy_retries: BusyRetriesOpt = 2,
    rotation_search: RotationSearchOpt = None,
    rotation_search_mode: RotationSearchModeOpt = None,
    threads: ThreadsOpt = None,
) -> None:
    """Register a sequence of scans: each FRAME onto the one before it.

    In one process with the model loaded once, or through a running service
    with --server (the frames read here and uploaded, one request per step).
    Each step gives the relative pose T_{i-1}_i (source frame i -> target
    frame i-1, as `mfgnet register` gives it) and the accumulated
    T_0_i = T_0_{i-1} @ T_{i-1}_i (frame i in frame 0's coordinates). Every
    frame is checked (exists, a regular file, a known extension) before the
    first registration; one short progress line per step goes to standard
    error. A path may repeat (a frame registered onto itself gives about the
    identity).

    \b
    Exit codes:
    0 done (whether or not every step is reliable; see --require-reliable);
    2 bad input (fewer than two frames, a missing or unreadable frame, a bad
      option, an unknown model, a step refused by the server); the steps
      before the frame that failed are written;
    1 other failures (model integrity, an output that cannot be written,
      server unreachable or 5xx);
    3 with --require-reliable: every step registered, one or more not reliable.
    """
    from service.sequence import frame_problem, register_sequence

    if out == Path("-"):
        out = None
    for index, path in enumerate(frames):  # first: an unmatched shell glob (scans/*.ply) is one missing frame
        problem = frame_problem(path)
        if problem:
            fail(f"frame {index} {path}: {problem}")
    if len(frames) < 2:
        fail(f"a sequence needs at least two frames, got {len(frames)}: {', '.join(map(str, frames))}")
    _check_sequence_outputs(frames, out, kitti)
    _check_aligned_folder(frames, write_aligned)
    check_server_flags(server, model_dir, threads, ctx)
    options = registration_options(
        iterations, keypoints, refine, refine_points, drop_isolated, rotation_search, rotation_search_mode
    )
    with contextlib.ExitStack() as stack:
        if server:  # one connection for every step; .npy uploads, as register's default --binary
            client = stack.enter_context(server_client(server, api_key, timeout, busy_retries))

            def register_pair(src: np.ndarray, tgt: np.ndarray, guess: list | None) -> dict:
                return remote_record(client, src, tgt, model, {**options, "initial_transform": guess}, True)
        else:
            registrar = load_registrar(model, model_dir or [], threads)

            def register_pair(src: np.ndarray, tgt: np.ndarray, guess: list | None) -> dict:
                return local_record(registrar, src, tgt, {**options, "initial_transform": guess})

        clouds: dict[int, np.ndarray] = {}  # the frames read, kept for --write-aligned until written

        def read_frame(index: int, path: Path) -> np.ndarray:
            points = _read_frame(index, path)
            if write_aligned is not None:
                clouds[index] = points
            return points

        steps = register_sequence(frames, read_frame, register_pair, constant_velocity=constant_velocity)
        unreliable = _write_steps(steps, frames, out, kitti, write_aligned, clouds)
    written = ", ".join(str(path) for path in (out, kitti) if path is not None)
    rests = f" (every accumulated pose from step {unreliable[0]} on rests on an unreliable step)" if unreliable else ""
    typer.echo(
        f"{len(frames) - 1} steps, {len(unreliable)} not reliable{rests}" + (f"; wrote {written}" if written else ""),
        err=True,
    )
    if require_reliable and unreliable:
        which = f"step{'s' if len(unreliable) > 1 else ''} {', '.join(map(str, unreliable))}"
        typer.echo(f"mfgnet: {which} not reliable (--require-reliable)", err=True)
        raise typer.Exit(UNRELIABLE_EXIT)


def _write_steps(
    steps: Iterator[Step],
    frames: list[Path],
    out: Path | None,
    kitti: Path | None,
    aligned: Path | None = None,
    clouds: dict[int, np.ndarray] | None = None,
) -> list[int]:
    """Each step's JSON line (``out``, else standard output), KITTI line (``kitti``), aligned frame (into the folder
    ``aligned``, from the points read, ``clouds``: frame 0 as it is with the first step) and progress line as it
    comes; the indices of the steps that are not quality.reliable."""
    from service.sequence import kitti_line

    unreliable: list[int] = []
    with _open_output(out) as lines, _open_output(kitti, to_stdout=False) as poses:
        if poses is not None:
            _write_line(poses, kitti_line(np.eye(4)), kitti)  # frame 0: the origin of the map
        for step in _steps_or_fail(steps, frames):
            _write_line(lines, step.json_line(), out)
            if poses is not None:
                _write_line(poses, kitti_line(step.accumulated), kitti)
            if aligned is not None and clouds is not None:
                if step.index == 1:
                    write_aligned_cloud(aligned / aligned_name(frames[0]), frames[0], clouds[0], np.eye(3), np.zeros(3))
                for index in [index for index in clouds if index < step.index]:
                    del clouds[index]  # written: frame i - 1 only serves as a target
                T = step.accumulated  # [4, 4] T_0_i
                write_aligned_cloud(
                    aligned / aligned_name(step.source), step.source, clouds[step.index], T[:3, :3], T[:3, 3]
                )
            typer.echo(_step_progress(step, len(frames) - 1), err=True)
            if not step.reliable:
                unreliable.append(step.index)
    return unreliable


def _check_sequence_outputs(frames: list[Path], out: Path | None, kitti: Path | None) -> None:
    """Usage errors of ``--out`` and ``--kitti`` before any registration: a folder, a missing folder, the same file
    twice, or one of the frames (it would be overwritten)."""
    check_output_path(out, "--out")
    check_output_path(kitti, "--kitti")
    if kitti == Path("-"):
        fail("--kitti -: standard output holds the JSON lines; name a file")
    if out is not None and kitti is not None and same_file(out, kitti):
        fail(f"--out and --kitti are the same file, {out}")
    for path, option in ((out, "--out"), (kitti, "--kitti")):
        if path is not None and any(same_file(path, frame) for frame in frames):
            fail(f"{option} {path} is one of the frames; it would be overwritten")


def aligned_name(frame: Path) -> str:
    """The file name of ``frame`` moved (``mfgnet sequence --write-aligned``): its own name, where a writer is named by
    its extension (a ``.las``/``.laz``, ``.pts``, ``.ptx`` or ``.e57`` name only for content of that
    format), else its stem with ``.ply``."""
    from service.formats.moved import OWN_FORMAT_ONLY, source_format
    from service.pointcloud_io import SUFFIXES

    suffix = frame.suffix.lower()
    if suffix in SUFFIXES or (suffix in OWN_FORMAT_ONLY and source_format(frame) == OWN_FORMAT_ONLY[suffix]):
        return frame.name
    return frame.stem + ".ply"


def _check_aligned_folder(frames: list[Path], folder: Path | None) -> None:
    """Usage errors of ``--write-aligned DIR`` before any registration: not an existing folder, two frames of one
    name, an output that would overwrite a frame, or a frame written in its own format that its header says cannot be
    (:func:`service.cli.common.check_aligned_source`: an E57 file whose XML section cannot be rewritten, an ``.npy``
    or ``.npz`` array the writer refuses)."""
    if folder is None:
        return
    if not folder.is_dir():
        fail(f"--write-aligned {folder}: {'not a folder' if folder.exists() else 'no such folder'}")
    names: dict[str, Path] = {}
    inputs = {frame.resolve() for frame in frames}
    for frame in frames:
        name = aligned_name(frame)
        if name in names:
            fail(f"--write-aligned {folder}: frames {names[name]} and {frame} would both be written as {name}")
        names[name] = frame
        if (folder / name).resolve() in inputs:
            fail(f"--write-aligned {folder}: {folder / name} is one of the frames; it would be overwritten")
        check_aligned_source(frame, str(folder / name))


def _read_frame(index: int, path: Path) -> np.ndarray:
    """``[N, 3]`` float64 points of frame ``index``, or exit 2 naming the frame."""
    return read_cloud(path, f"frame {index} {path}")


def _steps_or_fail(steps: Iterator[Step], frames: list[Path]) -> Iterator[Step]:
    """``steps`` as they come; a pair the pipeline or the server refuses (too few points, ...) is exit 2 naming both
    frames, a server unreachable or failing exit 1 naming them too."""
    from service.errors import InputError

    index = 1  # the step being registered: frame index onto frame index - 1
    while True:
        try:
            step = next(steps)
        except StopIteration:
            return
        except (InputError, ServerError) as exc:
            fail(
                f"frame {index} {frames[index]} onto frame {index - 1} {frames[index - 1]}: {exc}",
                code=exc.code if isinstance(exc, ServerError) else 2,
            )
        yield step
        index += 1


@contextlib.contextmanager
def _open_output(path: Path | None, to_stdout: bool = True) -> Iterator[TextIO | None]:
    """``path`` opened for writing (exit 1 where it cannot be); without a path standard output, or ``None`` where
    ``to_stdout`` is false."""
    if path is None:
        yield sys.stdout if to_stdout else None
        return
    try:
        handle = path.open("w")
    except OSError as exc:
        fail(f"cannot write {path}: {exc.strerror or exc}", code=1)
    with handle:
        yield handle


def _write_line(handle: TextIO, line: str, path: Path | None) -> None:
    """``line`` and a newline, flushed at once: a long run's steps can be followed, and survive a later failure."""
    try:
        handle.write(line + "\n")
        handle.flush()
    except OSError as exc:
        fail(f"cannot write {path or 'standard output'}: {exc.strerror or exc}", code=1)


def _step_progress(step: Step, count: int) -> str:
    """One short line per step for standard error: the pair, reliable or not, the turn, how far the pose moves the
    source's centroid (not ``|t|``, which names the turn's centre as well) and the time."""
    turn = np.degrees(2 * np.arccos(min(1.0, abs(step.record["quaternion_xyzw"][3]))))
    shift = step.centroid_motion
    total = step.record["timing_ms"].get("total")
    state = "reliable" if step.reliable else "NOT reliable"
    if step.reliable and not step.accumulated_reliable:
        state += " (its accumulated pose rests on a step that is not)"
    return (
        f"[{step.index}/{count}] {step.source.name} -> {step.target.name}: {state}, turn {turn:.2f} deg, "
        f"centroid moved {shift:.4g}, {number(total, '.0f')} ms"
    )
