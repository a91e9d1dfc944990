"""A 4x4 pose read from a file, as ``mfgnet register --initial-transform`` and ``bench.make_pair --transform`` take
one: ``T_target_source`` (source -> target, ``target ~ R source + t``, the service's ``transform``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

TRANSFORM_TEXT_BYTES = 1 << 16  # a .txt pose: 16 numbers with comments fit many times over
SUFFIXES = (".json", ".npy", ".txt")


class TransformFileError(ValueError):
    """A pose file that cannot be read as a 4x4 matrix; the message says why, without the file's name (the caller
    names the option and the file: ``f"--initial-transform {path.name}: {error}"``)."""


def read_transform(path: Path) -> np.ndarray:
    """A float64 ``[4, 4]`` matrix from ``.json`` (a 4x4 list, or an object with ``transform``, as ``mfgnet register
    --out`` writes), ``.npy`` or ``.txt`` (four rows of four numbers, as ``np.savetxt`` and other registration tools
    write a pose; commas allowed, ``#`` comments); else :class:`TransformFileError`. Whether it is rigid is not
    checked here (:func:`service.checks.check_transform`)."""
    path = Path(path)
    if path.is_dir():
        raise TransformFileError("cannot read it: a folder, not a file")
    if path.exists() and not path.is_file():  # a FIFO's open() could block for ever
        raise TransformFileError("cannot read it: not a regular file")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise TransformFileError(f"expected a {', '.join(SUFFIXES[:-1])} or {SUFFIXES[-1]} file")
    try:
        if suffix == ".json":
            payload = json.loads(path.read_text())
            matrix = payload.get("transform") if isinstance(payload, dict) else payload
            if matrix is None:
                raise TransformFileError(
                    "JSON object has no 'transform' (expected a 4x4 list, or an object with 'transform' as an --out "
                    "file holds)"
                )
            T = np.asarray(matrix, dtype=np.float64)
        elif suffix == ".npy":
            T = np.load(path, allow_pickle=False, mmap_mode="r")  # mapped: a header's shape allocates nothing
        else:
            if path.stat().st_size > TRANSFORM_TEXT_BYTES:
                raise TransformFileError(f"over {TRANSFORM_TEXT_BYTES} bytes, not a 4x4 matrix")
            rows = [line.split("#", 1)[0].replace(",", " ").split() for line in path.read_text().splitlines()]
            T = np.asarray([[float(value) for value in row] for row in rows if row], dtype=np.float64)  # [4, 4]
        if not isinstance(T, np.ndarray) or T.shape != (4, 4):
            shape = list(T.shape) if isinstance(T, np.ndarray) else type(T).__name__
            raise TransformFileError(f"expected a 4x4 matrix, got {shape}")
        return np.array(T, dtype=np.float64)
    except TransformFileError:
        raise
    except OSError as exc:
        raise TransformFileError(f"cannot read it: {exc.strerror or exc}") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:  # not numbers, too deep, beyond float64
        raise TransformFileError(f"not a 4x4 matrix ({type(exc).__name__}: {str(exc)[:200]})") from None
