"""Property-based fuzzing of the readers: valid files of every format, cut short, bytes flipped or inserted, header
numbers replaced by extreme ones (counts of 10^18, negative, beyond 64 bits). ``read_cloud`` and
``check_declared_count`` raise only the formats' own errors (``PointCloudFormatError``, with an HTTP status of 400,
413, 415 or 422), and the pre-check keeps the file's position. A short derandomized run; the long run that found the
E57 cases of ``test_formats_e57_xml.py`` drew from the same mutations, 12,000 cases."""

from __future__ import annotations

import io
import re
from pathlib import Path

import hypothesis
import laspy
import numpy as np
import pye57
import pytest
from hypothesis import strategies as st

from service.formats import PointCloudFormatError, read_cloud, write_cloud
from service.formats.read import check_declared_count

XYZ = np.random.default_rng(1).normal(size=(40, 3)).astype(np.float32).astype(np.float64)
EXTREMES = [
    "0",
    "-1",
    "3",
    "4294967296",
    "9223372036854775808",
    "18446744073709551616",
    "1000000000000000000",
    "1e400",
    "nan",
    "",
]
WIDE = [0xFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 2**63 - 1, 2**64 - 1, 10**18]


def _seeds(folder: Path) -> dict[str, bytes]:
    for suffix in (".ply", ".pcd", ".npy", ".npz", ".xyz", ".csv"):
        write_cloud(folder / f"a{suffix}", XYZ)
    rows = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in XYZ)
    (folder / "ascii.ply").write_text(
        f"ply\nformat ascii 1.0\nelement vertex {len(XYZ)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"end_header\n{rows}"
    )
    (folder / "ascii.pcd").write_text(
        f"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(XYZ)}\nHEIGHT 1\nPOINTS {len(XYZ)}\n"
        f"DATA ascii\n{rows}"
    )
    (folder / "a.pts").write_text(f"{len(XYZ)}\n{rows}")
    (folder / "a.ptx").write_text("4\n10\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n" + rows)
    for suffix in (".las", ".laz"):
        header = laspy.LasHeader(point_format=3, version="1.2")
        header.scales = [0.001] * 3
        las = laspy.LasData(header)
        las.x, las.y, las.z = XYZ.T
        las.write(str(folder / f"a{suffix}"), laz_backend=laspy.LazBackend.Lazrs if suffix == ".laz" else None)
    with pye57.E57(str(folder / "a.e57"), mode="w") as e57:
        e57.write_scan_raw({f"cartesian{axis}": np.ascontiguousarray(XYZ[:, k]) for k, axis in enumerate("XYZ")})
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, bytes]:
    found = _seeds(tmp_path_factory.mktemp("seeds"))
    for name, data in found.items():
        assert len(read_cloud(data, name)) == len(XYZ), name
    return found


@st.composite
def mutated(draw, seeds: dict[str, bytes]) -> tuple[str, bytes]:
    name = draw(st.sampled_from(sorted(seeds)))
    data = bytearray(seeds[name])
    for op in draw(st.lists(st.sampled_from(["cut", "flip", "insert", "number", "wide"]), min_size=1, max_size=3)):
        head = min(len(data), 1024)
        if head == 0:
            break
        if op == "cut":
            del data[draw(st.integers(0, len(data) - 1)) :]
        elif op == "flip":
            data[draw(st.integers(0, head - 1))] ^= draw(st.integers(1, 255))
        elif op == "insert":
            at = draw(st.integers(0, head))
            data[at:at] = draw(st.binary(max_size=8))
        elif op == "number":
            numbers = [m.span() for m in re.finditer(rb"-?\d+(\.\d+)?", bytes(data[:head]))]
            if numbers:
                start, end = draw(st.sampled_from(numbers))
                data[start:end] = draw(st.sampled_from(EXTREMES)).encode()
        else:
            at, width = draw(st.integers(0, max(0, min(head, 256) - 8))), draw(st.sampled_from([2, 4, 8]))
            data[at : at + width] = (draw(st.sampled_from(WIDE)) % (1 << 8 * width)).to_bytes(width, "little")
    return name, bytes(data)


def test_mutated_files_of_every_format_raise_only_format_errors(seeds) -> None:
    statuses: set[int] = set()

    @hypothesis.given(case=mutated(seeds), max_points=st.sampled_from([None, 2_000_000, 30]))
    @hypothesis.settings(
        max_examples=300,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=list(hypothesis.HealthCheck),
    )
    def check(case: tuple[str, bytes], max_points: int | None) -> None:
        name, data = case
        f = io.BytesIO(data)
        try:
            check_declared_count(f, name, max_points or 2_000_000)
        except PointCloudFormatError as exc:
            assert exc.status == 413
        assert f.tell() == 0
        try:
            read_cloud(data, name, max_points)
        except PointCloudFormatError as exc:
            assert exc.status in (400, 413, 415, 422)
            assert str(exc).startswith(f"{name}: ")
            statuses.add(exc.status)

    check()
    assert {400, 422} <= statuses  # the mutations reach the readers' checks, not only detection


@pytest.mark.parametrize(
    "text",
    [
        "9223372036854775808\n1 2 3\n",  # a PTS count beyond sys.maxsize
        "99999999999999999999\n99999999999\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n1 2 3 0\n",
    ],
    ids=["pts", "ptx"],
)
def test_leica_counts_beyond_sys_maxsize_are_format_errors_without_a_limit(text: str) -> None:
    """Found by the long run: without a point limit (the CLI reads so), a count beyond ``sys.maxsize`` reached
    ``itertools.islice`` as its stop and raised ValueError."""
    with pytest.raises(PointCloudFormatError, match=r"points; 1 rows follow"):
        read_cloud(text.encode(), "a")
