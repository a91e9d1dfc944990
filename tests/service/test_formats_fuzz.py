"""Property-based fuzzing of the readers: valid files of every format, cut short, bytes flipped or inserted, header
numbers replaced by extreme ones (counts of 10^18, negative, beyond 64 bits). ``read_cloud`` and
``check_declared_count`` raise only the formats' own errors (``PointCloudFormatError``, with an HTTP status of 400,
413, 415 or 422), and the pre-check keeps the file's position. An E57's XML section is mutated too, its pages rebuilt
with their checksums so that the e57 library parses it. A short derandomized run, and a long random one (``-m slow``),
which found the E57 offset and PTS/PTX count errors fixed here."""

from __future__ import annotations

import io
import os
import re
import time
from pathlib import Path

import hypothesis
import laspy
import numpy as np
import pye57
import pytest
from e57_xml import with_xml, xml_of
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
    in_xml = name.endswith(".e57") and draw(
        st.booleans()
    )  # the XML section, its pages rebuilt: it reaches the e57 library
    data = bytearray(xml_of(seeds[name]) if in_xml else seeds[name])
    for op in draw(st.lists(st.sampled_from(["cut", "flip", "insert", "number", "wide"]), min_size=1, max_size=3)):
        head = len(data) if in_xml else min(len(data), 1024)
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
    return name, with_xml(seeds[name], bytes(data)) if in_xml else bytes(data)


def fuzz(seeds: dict[str, bytes], cases: int, derandomize: bool) -> dict:
    """``cases`` mutated files through ``check_declared_count`` and ``read_cloud``; raises on the first error that is
    not a format error. The statuses seen, and the slowest case's seconds and seed."""
    statuses: set[int] = set()
    slowest = (0.0, "")

    @hypothesis.given(case=mutated(seeds), max_points=st.sampled_from([None, 2_000_000, 30]))
    @hypothesis.settings(
        max_examples=cases,
        derandomize=derandomize,
        deadline=None,
        database=None,
        print_blob=True,
        suppress_health_check=list(hypothesis.HealthCheck),
    )
    def check(case: tuple[str, bytes], max_points: int | None) -> None:
        nonlocal slowest
        name, data = case
        started = time.perf_counter()
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
        slowest = max(slowest, (time.perf_counter() - started, name))

    check()
    return {"statuses": sorted(statuses), "slowest_s": round(slowest[0], 3), "slowest": slowest[1]}


def test_mutated_files_of_every_format_raise_only_format_errors(seeds) -> None:
    result = fuzz(seeds, cases=300, derandomize=True)
    assert {400, 422} <= set(result["statuses"])  # the mutations reach the readers' checks, not only detection


@pytest.mark.slow
def test_mutated_files_long_run(seeds) -> None:
    """Random draws, ``MFGNET_FUZZ_CASES`` of them (20,000 took 49 s)."""
    result = fuzz(seeds, cases=int(os.environ.get("MFGNET_FUZZ_CASES", "20000")), derandomize=False)
    print(result)
    assert result["slowest_s"] < 10, result


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


def test_an_npz_of_a_zip_version_beyond_pythons_is_a_format_error(tmp_path) -> None:
    """Found by the long run: zipfile raises NotImplementedError for a member whose 'version needed to extract' is
    beyond 6.3, from the archive's directory (read when the archive is opened)."""
    np.savez(tmp_path / "a.npz", points=XYZ)
    data = bytearray((tmp_path / "a.npz").read_bytes())
    directory = data.index(b"PK\x01\x02")  # the central directory's entry: its version needed to extract at +6
    data[directory + 6 : directory + 8] = (109).to_bytes(2, "little")
    with pytest.raises(PointCloudFormatError, match=r"not a valid \.npz archive \(zip file version 10\.9\)"):
        read_cloud(bytes(data), "a.npz")
    assert check_declared_count(io.BytesIO(data), "a.npz", 9) is None  # the reader's to name
