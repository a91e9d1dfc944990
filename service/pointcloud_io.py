"""Reading and writing point clouds: PLY, PCD, XYZ/TXT/CSV, NPY and NPZ (numpy only).

Every reader returns finite ``float32 (N, 3)`` coordinates with ``N >= 1`` and raises
:class:`PointCloudFormatError` (a ``ValueError``) with the file's name and the reason otherwise.
Only the ``x, y, z`` coordinates are kept; colours, normals, faces and other fields are skipped.

=========================  ===============================================  ========================
extension                  read                                             written as
=========================  ===============================================  ========================
``.ply``                   ascii, binary_little_endian, binary_big_endian   binary little endian f4
``.pcd``                   ascii, binary, binary_compressed (LZF)           binary f4
``.xyz`` ``.txt`` ``.csv``  whitespace or comma separated, first 3 columns,  ``%.9g`` text (csv:
                           one non-numeric header line and ``#`` comments   comma + ``x,y,z`` line)
                           skipped
``.npy``                   numeric ``(N, >=3)`` or fields x, y, z; no       float32 ``(N, 3)``
                           pickles
``.npz``                   key ``points``, else the only array              key ``points``
=========================  ===============================================  ========================
"""

from __future__ import annotations

import io
import os
import re
import struct
import zipfile
from pathlib import Path

import numpy as np

SUFFIXES = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz")


class PointCloudFormatError(ValueError):
    """A point-cloud file that cannot be read, or points that cannot be written."""


def read_points(path: str | os.PathLike[str]) -> np.ndarray:
    """``float32 (N, 3)`` coordinates of the cloud in ``path``; the format comes from the extension.

    Raises:
        PointCloudFormatError: unknown extension, corrupt file, fewer than 3 columns, no points,
            NaN/Inf values.
        OSError: the file cannot be opened.
    """
    path = Path(path)
    _reader_for(path.suffix, path.name)  # unknown extension: fail before reading the file
    return parse_points(path.read_bytes(), path.suffix, name=path.name)


def parse_points(data: bytes, suffix: str, name: str = "<bytes>") -> np.ndarray:
    """Like :func:`read_points` for the ``data`` of a file (e.g. an upload) whose extension is ``suffix``."""
    reader = _reader_for(suffix, name)
    try:
        points = reader(data)
    except PointCloudFormatError as exc:
        raise PointCloudFormatError(f"{name}: {exc}") from None
    except (ValueError, IndexError, KeyError, TypeError, struct.error, EOFError, zipfile.BadZipFile) as exc:
        raise PointCloudFormatError(f"{name}: corrupt or unreadable {suffix.lower()} file ({exc})") from exc
    return _checked(points, name)


def write_points(path: str | os.PathLike[str], points: np.ndarray) -> None:
    """Write ``points (N, 3)`` (stored as float32) in the format given by the extension of ``path``.

    Raises:
        PointCloudFormatError: unknown extension, wrong shape, no points, NaN/Inf values.
    """
    path = Path(path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise PointCloudFormatError(f"{path.name}: unknown extension {path.suffix!r}; expected {SUFFIXES}")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PointCloudFormatError(f"{path.name}: points must be (N, 3), got {points.shape}")
    xyz = _checked(points, path.name)  # [N, 3] float32
    with open(path, "wb") as f:
        writer(f, xyz, path.suffix.lower())


def _reader_for(suffix: str, name: str):
    reader = _READERS.get(suffix.lower())
    if reader is None:
        raise PointCloudFormatError(f"{name}: unknown extension {suffix!r}; expected {SUFFIXES}")
    return reader


def _checked(points: np.ndarray, name: str) -> np.ndarray:
    """``points`` as finite float32 ``(N, 3)``, ``N >= 1``, or a :class:`PointCloudFormatError`."""
    if points.dtype.kind not in "fiu":
        raise PointCloudFormatError(f"{name}: coordinates must be numeric, got dtype {points.dtype}")
    if points.ndim != 2 or points.shape[1] < 3:
        raise PointCloudFormatError(f"{name}: need at least 3 columns (x, y, z), got shape {points.shape}")
    if points.shape[0] == 0:
        raise PointCloudFormatError(f"{name}: the cloud is empty")
    with np.errstate(over="ignore"):  # values beyond float32 become inf and are refused below
        xyz = points[:, :3].astype(np.float32)  # [N, 3]
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise PointCloudFormatError(
            f"{name}: {int(bad.sum())} point(s) with NaN/Inf coordinates (or beyond float32), "
            f"first at index {int(np.argmax(bad))}"
        )
    return xyz


def _split_header_line(data: bytes, start: int) -> tuple[str, int]:
    """The text line starting at byte ``start`` and the offset just after its newline."""
    end = data.find(b"\n", start)
    if end < 0:
        raise PointCloudFormatError("header is not terminated")
    return data[start:end].decode("ascii").strip(), end + 1


# ----------------------------------------------------------------------------------------------- PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def _read_ply(data: bytes) -> np.ndarray:
    if not data.startswith(b"ply"):
        raise PointCloudFormatError("not a PLY file (no 'ply' magic)")
    # Each element: (name, count, properties); a property is (name, type) or (name, (count type, item type)).
    elements: list[tuple[str, int, list[tuple[str, str | tuple[str, str]]]]] = []
    fmt = None
    offset = 0
    while True:
        line, offset = _split_header_line(data, offset)
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            if len(words) < 2 or words[1] not in _PLY_FORMATS:
                raise PointCloudFormatError(f"unsupported PLY format line {line!r}")
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PointCloudFormatError(f"PLY property before any element: {line!r}")
            if words[1] == "list":
                prop = (words[4], (_ply_type(words[2]), _ply_type(words[3])))
            else:
                prop = (words[2], _ply_type(words[1]))
            elements[-1][2].append(prop)
        else:
            raise PointCloudFormatError(f"unexpected PLY header line {line!r}")
    if fmt is None:
        raise PointCloudFormatError("PLY header has no format line")
    if "vertex" not in [e[0] for e in elements]:
        raise PointCloudFormatError("PLY file has no vertex element")
    vertex_props = [p[0] for p in next(e for e in elements if e[0] == "vertex")[2]]
    missing = [axis for axis in "xyz" if axis not in vertex_props]
    if missing:
        raise PointCloudFormatError(f"PLY vertex element lacks properties {missing}")
    columns = [vertex_props.index(axis) for axis in "xyz"]
    if fmt == "ascii":
        return _read_ply_ascii(data[offset:], elements, columns)
    return _read_ply_binary(data, offset, _PLY_FORMATS[fmt], elements, columns)


def _ply_type(name: str) -> str:
    if name not in _PLY_TYPES:
        raise PointCloudFormatError(f"unknown PLY property type {name!r}")
    return _PLY_TYPES[name]


def _read_ply_ascii(body: bytes, elements, columns: list[int]) -> np.ndarray:
    tokens = body.split()
    pos = 0
    for name, count, props in elements:
        has_list = any(isinstance(kind, tuple) for _, kind in props)
        if not has_list:
            width = len(props)
            if name == "vertex":
                if pos + count * width > len(tokens):
                    raise PointCloudFormatError(f"PLY body ends inside the vertex element ({count} expected)")
                values = np.array(tokens[pos : pos + count * width], dtype=np.float64)
                return values.reshape(count, width)[:, columns]
            pos += count * width
            continue
        rows = []
        for _ in range(count):  # list properties: walk the records one by one
            row = []
            for _, kind in props:
                if isinstance(kind, tuple):
                    pos += int(tokens[pos]) + 1
                    row.append(np.nan)
                else:
                    row.append(float(tokens[pos]))
                    pos += 1
            rows.append(row)
        if name == "vertex":
            return np.array(rows, dtype=np.float64).reshape(count, len(props))[:, columns]
    raise PointCloudFormatError("PLY file has no vertex element")  # unreachable: checked by the caller


def _read_ply_binary(data: bytes, offset: int, order: str, elements, columns: list[int]) -> np.ndarray:
    for name, count, props in elements:
        has_list = any(isinstance(kind, tuple) for _, kind in props)
        if not has_list:
            record = np.dtype([(f"p{i}", order + kind) for i, (_, kind) in enumerate(props)])
            if offset + count * record.itemsize > len(data):
                raise PointCloudFormatError(
                    f"PLY body too short: element {name!r} needs {count * record.itemsize} bytes at offset "
                    f"{offset}, the file has {len(data)}"
                )
            if name == "vertex":
                table = np.frombuffer(data, dtype=record, count=count, offset=offset)
                return np.stack([table[f"p{c}"].astype(np.float64) for c in columns], axis=1)
            offset += count * record.itemsize
            continue
        rows = []
        for _ in range(count):  # list properties: walk the records one by one
            row = []
            for _, kind in props:
                if isinstance(kind, tuple):
                    count_type, item_type = (np.dtype(order + k) for k in kind)
                    n_items = int(np.frombuffer(data, dtype=count_type, count=1, offset=offset)[0])
                    offset += count_type.itemsize + n_items * item_type.itemsize
                    row.append(np.nan)
                else:
                    value_type = np.dtype(order + kind)
                    row.append(float(np.frombuffer(data, dtype=value_type, count=1, offset=offset)[0]))
                    offset += value_type.itemsize
            rows.append(row)
        if offset > len(data):
            raise PointCloudFormatError(f"PLY body too short for element {name!r}")
        if name == "vertex":
            return np.array(rows, dtype=np.float64).reshape(count, len(props))[:, columns]
    raise PointCloudFormatError("PLY file has no vertex element")  # unreachable: checked by the caller


def _write_ply(f, xyz: np.ndarray, suffix: str) -> None:
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by mfgnet\n"
        f"element vertex {xyz.shape[0]}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    f.write(header.encode("ascii"))
    f.write(xyz.astype("<f4").tobytes())


# ----------------------------------------------------------------------------------------------- PCD

_PCD_KINDS = {"F": "f", "I": "i", "U": "u"}


def _read_pcd(data: bytes) -> np.ndarray:
    header: dict[str, list[str]] = {}
    offset = 0
    while True:
        line, offset = _split_header_line(data, offset)
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in header:
            raise PointCloudFormatError(f"PCD header lacks {key}")
    fields = header["FIELDS"]
    sizes = [int(s) for s in header["SIZE"]]
    kinds = header["TYPE"]
    counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
    if not len(fields) == len(sizes) == len(kinds) == len(counts):
        raise PointCloudFormatError("PCD FIELDS, SIZE, TYPE and COUNT have different lengths")
    if "POINTS" in header:
        n_points = int(header["POINTS"][0])
    else:
        n_points = int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0])
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        raise PointCloudFormatError(f"PCD file lacks fields {missing}")
    dtypes = []
    for field, size, kind in zip(fields, sizes, kinds, strict=True):
        if kind.upper() not in _PCD_KINDS or size not in (1, 2, 4, 8):
            raise PointCloudFormatError(f"unsupported PCD field {field!r}: TYPE {kind} SIZE {size}")
        dtypes.append(np.dtype("<" + _PCD_KINDS[kind.upper()] + str(size)))
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    if mode == "ascii":
        values = np.array(data[offset:].split(), dtype=np.float64)
        width = sum(counts)
        if values.size != n_points * width:
            raise PointCloudFormatError(f"PCD ascii body has {values.size} values, not {n_points} x {width}")
        starts = np.cumsum([0, *counts])
        return values.reshape(n_points, width)[:, [int(starts[fields.index(a)]) for a in "xyz"]]
    if mode == "binary":
        record = np.dtype([(f"f{i}", dt, (c,)) for i, (dt, c) in enumerate(zip(dtypes, counts, strict=True))])
        if offset + n_points * record.itemsize > len(data):
            raise PointCloudFormatError(
                f"PCD binary body has {len(data) - offset} bytes, expected {n_points * record.itemsize}"
            )
        table = np.frombuffer(data, dtype=record, count=n_points, offset=offset)
        return np.stack([table[f"f{fields.index(a)}"][:, 0].astype(np.float64) for a in "xyz"], axis=1)
    if mode == "binary_compressed":
        compressed_size, raw_size = struct.unpack_from("<II", data, offset)
        compressed = data[offset + 8 : offset + 8 + compressed_size]
        if len(compressed) != compressed_size:
            raise PointCloudFormatError(f"PCD body cut short: {len(compressed)} of {compressed_size} bytes")
        raw = lzf_decompress(compressed, raw_size)
        # Field-major layout: all points' values of field 0, then of field 1, ...
        block_sizes = [n_points * dt.itemsize * c for dt, c in zip(dtypes, counts, strict=True)]
        if sum(block_sizes) != raw_size:
            raise PointCloudFormatError(f"PCD decompressed size {raw_size} does not match the fields")
        starts = np.cumsum([0, *block_sizes])
        columns = []
        for axis in "xyz":
            i = fields.index(axis)
            block = np.frombuffer(raw, dtype=dtypes[i], count=n_points * counts[i], offset=int(starts[i]))
            columns.append(block.reshape(n_points, counts[i])[:, 0].astype(np.float64))
        return np.stack(columns, axis=1)
    raise PointCloudFormatError(f"unsupported PCD DATA {mode!r}")


def lzf_decompress(compressed: bytes, raw_size: int) -> bytes:
    """Decompress LZF data (liblzf's format, as used by PCD ``binary_compressed``) of ``raw_size`` bytes.

    A control byte ``c < 32`` is followed by ``c + 1`` literal bytes; otherwise ``c >> 5`` (plus one
    more byte when it is 7) gives a length ``- 2`` and ``(c & 31) << 8 | next byte`` a distance ``- 1``
    back into the output, from which the bytes are copied (possibly overlapping the copy itself).
    """
    out = bytearray()
    i, n = 0, len(compressed)
    while i < n:
        ctrl = compressed[i]
        i += 1
        if ctrl < 32:
            length = ctrl + 1
            if i + length > n:
                raise PointCloudFormatError("LZF literal run past the end of the data")
            out += compressed[i : i + length]
            i += length
        else:
            length = ctrl >> 5
            if length == 7:
                if i >= n:
                    raise PointCloudFormatError("LZF back-reference cut short")
                length += compressed[i]
                i += 1
            if i >= n:
                raise PointCloudFormatError("LZF back-reference cut short")
            ref = len(out) - ((ctrl & 0x1F) << 8) - compressed[i] - 1
            i += 1
            length += 2
            if ref < 0:
                raise PointCloudFormatError("LZF back-reference before the start of the data")
            period = len(out) - ref
            if length <= period:
                out += out[ref : ref + length]
            else:  # the copy overlaps its own output: repeat the last `period` bytes
                pattern = bytes(out[ref:])
                out += (pattern * (length // period + 1))[:length]
        if len(out) > raw_size:
            raise PointCloudFormatError(f"LZF data expands beyond the declared {raw_size} bytes")
    if len(out) != raw_size:
        raise PointCloudFormatError(f"LZF data expands to {len(out)} bytes, expected {raw_size}")
    return bytes(out)


def _write_pcd(f, xyz: np.ndarray, suffix: str) -> None:
    n = xyz.shape[0]
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by mfgnet)\nVERSION 0.7\nFIELDS x y z\n"
        f"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        "DATA binary\n"
    )
    f.write(header.encode("ascii"))
    f.write(xyz.astype("<f4").tobytes())


# ------------------------------------------------------------------------------------------ text

_SEPARATORS = re.compile(r"[,\s]+")


def _read_text(data: bytes) -> np.ndarray:
    lines = [line.strip() for line in data.decode("utf-8-sig").splitlines()]
    lines = [line for line in lines if line and not line.startswith("#")]
    rows = [_SEPARATORS.split(line) for line in lines]
    if rows and not _is_numeric(rows[0]):
        rows = rows[1:]  # header line
    for number, row in enumerate(rows):
        if len(row) < 3:
            raise PointCloudFormatError(f"data row {number + 1} has {len(row)} column(s), need at least 3")
    if not rows:
        return np.zeros((0, 3))
    return np.array([row[:3] for row in rows], dtype=np.float64)


def _is_numeric(tokens: list[str]) -> bool:
    try:
        [float(token) for token in tokens]
    except ValueError:
        return False
    return True


def _write_text(f, xyz: np.ndarray, suffix: str) -> None:
    if suffix == ".csv":
        np.savetxt(f, xyz, fmt="%.9g", delimiter=",", header="x,y,z", comments="")
    else:
        np.savetxt(f, xyz, fmt="%.9g", delimiter=" ")


# ------------------------------------------------------------------------------------------ numpy


def _read_npy(data: bytes) -> np.ndarray:
    loaded = _load(lambda: np.load(io.BytesIO(data), allow_pickle=False))
    if not isinstance(loaded, np.ndarray):
        raise PointCloudFormatError("not a single .npy array")
    return _array_points(loaded)


def _read_npz(data: bytes) -> np.ndarray:
    archive = _load(lambda: np.load(io.BytesIO(data), allow_pickle=False))
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise PointCloudFormatError("not an .npz archive")
    with archive:
        keys = list(archive.files)
        if "points" in keys:
            key = "points"
        elif len(keys) == 1:
            key = keys[0]
        else:
            raise PointCloudFormatError(f"npz archive has no 'points' array and several arrays: {keys}")
        return _array_points(_load(lambda: archive[key]))


def _load(load):
    """``load()``, turning numpy's refusal of pickled objects into a clear error."""
    try:
        return load()
    except ValueError as exc:
        if "Object arrays" in str(exc):
            raise PointCloudFormatError("object arrays are refused (they need pickle)") from None
        if "pickled data" in str(exc):
            raise PointCloudFormatError("not a numpy file (pickled data is refused)") from None
        raise


def _array_points(array: np.ndarray) -> np.ndarray:
    if array.dtype.names is not None:  # structured array with x, y, z fields
        missing = [axis for axis in "xyz" if axis not in array.dtype.names]
        if missing:
            raise PointCloudFormatError(f"structured array lacks fields {missing}")
        return np.stack([array[axis].reshape(-1).astype(np.float64) for axis in "xyz"], axis=1)
    if array.dtype.kind == "O":
        raise PointCloudFormatError("object arrays are refused")
    return array


def _write_npy(f, xyz: np.ndarray, suffix: str) -> None:
    np.save(f, xyz, allow_pickle=False)


def _write_npz(f, xyz: np.ndarray, suffix: str) -> None:
    np.savez(f, points=xyz)


_READERS = {
    ".ply": _read_ply,
    ".pcd": _read_pcd,
    ".xyz": _read_text,
    ".txt": _read_text,
    ".csv": _read_text,
    ".npy": _read_npy,
    ".npz": _read_npz,
}
_WRITERS = {
    ".ply": _write_ply,
    ".pcd": _write_pcd,
    ".xyz": _write_text,
    ".txt": _write_text,
    ".csv": _write_text,
    ".npy": _write_npy,
    ".npz": _write_npz,
}
