"""Terrestrial laser scanner files: E57 (written by pye57 / libE57Format, read by the e57 library) and Leica PTS / PTX
text, read by
``read_cloud`` and uploaded to a real server: scans brought into the file's frame by their poses, points without a
return left out, the point limit from the header, and damaged files a 4xx naming the problem."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pye57
import pytest
from api_server import LIMITED, MODEL, assert_error, limited_server, synthetic_pair
from e57_xml import HEADER, _paged, with_xml, xml_of
from pye57 import libe57

from service.formats import PointCloudFormatError, TooManyPointsError, read_cloud
from service.formats import e57 as e57_reader
from service.sequence import frame_problem

PAIR = synthetic_pair(5)
# float32 values: pye57 stores coordinates in single precision, so these read back exactly
SOURCE, TARGET = PAIR.source.astype(np.float32).astype(np.float64), PAIR.target.astype(np.float32).astype(np.float64)
OPTIONS = {"model": MODEL, "rotation_search": "false"}
QUARTER_TURN_Z = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # w, x, y, z: 90 degrees about z


def write_e57(path: Path, scans: list[dict]) -> None:
    """Scans of ``{"xyz": [n, 3], "invalid": [n] or None, "rotation": wxyz, "translation": [3]}`` via pye57's writer."""
    with pye57.E57(str(path), mode="w") as e57:
        for scan in scans:
            data = {f"cartesian{axis}": np.ascontiguousarray(scan["xyz"][:, k]) for k, axis in enumerate("XYZ")}
            if scan.get("invalid") is not None:
                data["cartesianInvalidState"] = scan["invalid"].astype(np.int8)
            e57.write_scan_raw(
                data,
                rotation=scan.get("rotation", np.array([1.0, 0, 0, 0])),
                translation=scan.get("translation", np.zeros(3)),
            )


def write_spherical_e57(path: Path, rae: np.ndarray, invalid: np.ndarray) -> None:
    """One scan of range, azimuth, elevation (double) and sphericalInvalidState, through libE57Format's nodes (pye57's
    writer writes cartesian fields only)."""
    e57 = pye57.E57(str(path), mode="w")
    imf = e57.image_file
    scan = libe57.StructureNode(imf)
    scan.set("guid", libe57.StringNode(imf, "{spherical-scan}"))
    prototype = libe57.StructureNode(imf)
    for name in ("sphericalRange", "sphericalAzimuth", "sphericalElevation"):
        prototype.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
    prototype.set("sphericalInvalidState", libe57.IntegerNode(imf, 0, 0, 2))
    points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
    scan.set("points", points)
    e57.data3d.append(scan)
    columns = [np.ascontiguousarray(rae[:, k]) for k in range(3)] + [invalid.astype(np.int8)]
    names = ["sphericalRange", "sphericalAzimuth", "sphericalElevation", "sphericalInvalidState"]
    buffers = libe57.VectorSourceDestBuffer()
    for name, column in zip(names, columns, strict=True):
        buffers.append(libe57.SourceDestBuffer(imf, name, column, len(column), True, True))
    writer = points.writer(buffers)
    writer.write(len(rae))
    writer.close()
    e57.close()


def write_typed_e57(path: Path, scans: list[dict[str, tuple]]) -> None:
    """Scans of fields ``{name: (kind, column)}`` through libE57Format's nodes, each kind ``"single"``, ``"double"``,
    ``("integer", minimum, maximum)`` or ``("scaled", minimum, maximum, scale)``."""
    e57 = pye57.E57(str(path), mode="w")
    imf = e57.image_file
    for number, fields in enumerate(scans):
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, f"{{typed-{number}}}"))
        prototype = libe57.StructureNode(imf)
        columns = []
        for name, (kind, column) in fields.items():
            if kind in ("single", "double"):
                precision = libe57.E57_SINGLE if kind == "single" else libe57.E57_DOUBLE
                prototype.set(name, libe57.FloatNode(imf, 0.0, precision))
                columns.append(np.ascontiguousarray(column, dtype=np.float32 if kind == "single" else np.float64))
            elif kind[0] == "integer":
                prototype.set(name, libe57.IntegerNode(imf, kind[1], kind[1], kind[2]))
                # long long: pye57's buffer takes numpy's int64 (format 'l') but writes its values as 0
                columns.append(np.ascontiguousarray(column, dtype=np.longlong))
            else:
                prototype.set(name, libe57.ScaledIntegerNode(imf, kind[1], kind[1], kind[2], kind[3], 0.0))
                columns.append(np.ascontiguousarray(column, dtype=np.float64))
        points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
        scan.set("points", points)
        e57.data3d.append(scan)
        buffers = libe57.VectorSourceDestBuffer()
        for (name, (kind, _)), column in zip(fields.items(), columns, strict=True):
            buffers.append(libe57.SourceDestBuffer(imf, name, column, len(column), True, kind[0] == "scaled"))
        writer = points.writer(buffers)
        writer.write(len(columns[0]))
        writer.close()
    e57.close()


def with_record_count(data: bytes, scan: int, count: int) -> bytes:
    """The E57 file ``data`` with scan ``scan``'s ``recordCount`` set to ``count`` (pages rebuilt)."""
    xml = xml_of(data)
    found = list(re.finditer(rb'recordCount="([0-9]+)"', xml))[scan]
    return with_xml(data, xml[: found.start(1)] + str(count).encode() + xml[found.end(1) :])


def pts_text(xyz: np.ndarray) -> str:
    """Open3D's / Cyclone's PTS: the count, then x y z intensity r g b."""
    return f"{len(xyz)}\n" + "".join(f"{x:.17g} {y:.17g} {z:.17g} 0.5 10 20 30\n" for x, y, z in xyz)


def ptx_text(xyz_scanner: np.ndarray, matrix: np.ndarray, columns: int) -> str:
    """One PTX scan: its header (the 4x4 ``matrix`` in PTX's row-vector layout) and ``x y z intensity`` rows."""
    rows = len(xyz_scanner) // columns
    header = [str(columns), str(rows)] + [" ".join(f"{v:.17g}" for v in matrix[k, :3]) for k in (3, 0, 1, 2)]
    header += [" ".join(f"{v:.17g}" for v in matrix[k]) for k in range(4)]
    return "\n".join(header) + "\n" + "".join(f"{x:.17g} {y:.17g} {z:.17g} 0.25\n" for x, y, z in xyz_scanner)


def rotation_z(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


# ------------------------------------------------------------------------------------------------------------- E57


def test_e57_scans_are_moved_by_their_poses_and_invalid_points_are_left_out(tmp_path) -> None:
    first, second = SOURCE[:300], SOURCE[300:]
    invalid = np.zeros(len(first), dtype=np.int8)
    invalid[::7] = 2  # no return
    invalid[3::7] = 1  # a direction only
    translation = np.array([10.0, -2.0, 0.5])
    write_e57(
        tmp_path / "two.e57",
        [
            {"xyz": first, "invalid": invalid, "rotation": QUARTER_TURN_Z, "translation": translation},
            {"xyz": second},
        ],
    )
    expected = np.vstack([first[invalid == 0] @ rotation_z(90).T + translation, second])
    from_path = read_cloud(tmp_path / "two.e57")
    np.testing.assert_allclose(from_path, expected, atol=1e-9)
    from_bytes = read_cloud((tmp_path / "two.e57").read_bytes(), "two.e57")  # the upload path: a temporary copy
    np.testing.assert_array_equal(from_bytes, from_path)


def test_e57_spherical_coordinates_are_converted_as_the_standard_defines(tmp_path) -> None:
    rae = np.array([[2.0, 0.0, 0.0], [3.0, np.pi / 2, 0.0], [4.0, 0.3, np.pi / 2], [5.0, 1.0, 0.2], [6.0, 2.0, 0.1]])
    write_spherical_e57(tmp_path / "s.e57", rae, invalid=np.array([0, 0, 0, 0, 2]))
    xyz = read_cloud(tmp_path / "s.e57")
    r, azimuth, elevation = rae[:4].T
    expected = np.stack(
        [r * np.cos(elevation) * np.cos(azimuth), r * np.cos(elevation) * np.sin(azimuth), r * np.sin(elevation)],
        axis=1,
    )
    np.testing.assert_allclose(xyz, expected, atol=1e-12)
    np.testing.assert_allclose(xyz[:3], [[2, 0, 0], [0, 3, 0], [0, 0, 4]], atol=1e-12)


def test_e57_point_limit_comes_from_the_headers_before_any_point_is_read(tmp_path, monkeypatch) -> None:
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE[:200]}, {"xyz": SOURCE[200:450]}])
    monkeypatch.setattr(e57_reader, "_read_points", lambda *args: pytest.fail("points read past the limit"))
    with pytest.raises(TooManyPointsError, match=r"a\.e57: has 450 points; the limit is 449") as caught:
        read_cloud(tmp_path / "a.e57", max_points=449)
    assert (caught.value.count, caught.value.limit) == (450, 449)


def test_e57_with_only_invalid_points_is_a_422_saying_so(tmp_path) -> None:
    write_spherical_e57(tmp_path / "a.e57", np.ones((10, 3)), invalid=np.full(10, 2))  # pye57 refuses to write it
    with pytest.raises(PointCloudFormatError, match="all 10 points of the E57 file are marked invalid") as caught:
        read_cloud(tmp_path / "a.e57")
    assert caught.value.status == 422


@pytest.mark.parametrize("damage", ["truncated", "flipped byte"])
def test_damaged_e57_is_a_400_naming_the_problem(tmp_path, damage) -> None:
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}])
    data = bytearray((tmp_path / "a.e57").read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    else:
        data[len(data) // 2] ^= 0xFF
    with pytest.raises(PointCloudFormatError) as caught:
        read_cloud(bytes(data), "a.e57")
    assert caught.value.status == 400
    words = "the E57 file is cut short" if damage == "truncated" else "invalid checksum"
    assert str(caught.value).startswith("a.e57: ") and words in str(caught.value)
    assert "/tmp" not in str(caught.value)  # the temporary copy's name stays out of the message


def test_a_panic_of_the_e57_library_is_a_400(tmp_path) -> None:
    """Damaged point data makes ``e57.read_points`` panic: ``pyo3_runtime.PanicException``, a BaseException that an
    ``except Exception`` lets through (a 500, or the end of the worker's thread)."""
    e57 = pytest.importorskip("e57")
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}])
    data = bytearray((tmp_path / "a.e57").read_bytes())
    data[100] ^= 0xFF  # in the first scan's points: its page's checksum no longer matches
    (tmp_path / "a.e57").write_bytes(data)
    with pytest.raises(BaseException) as panic:
        e57.read_points(str(tmp_path / "a.e57"))
    assert type(panic.value).__name__ == "PanicException" and not isinstance(panic.value, Exception)
    for source in (tmp_path / "a.e57", bytes(data)):  # the file's own path, and an upload's temporary copy
        with pytest.raises(PointCloudFormatError) as caught:
            read_cloud(source, "a.e57")
        assert caught.value.status == 400
        assert str(caught.value).startswith("a.e57: not a readable E57 file (") and "invalid checksum" in str(
            caught.value
        )
        assert "/tmp" not in str(caught.value) and "Read {" not in str(caught.value)


def test_an_e57_with_an_empty_scan_is_a_400_naming_it_and_only_empty_scans_a_422(tmp_path) -> None:
    """The library cannot read a file holding a scan of no points (libE57Format writes its section offset as 0, and
    the library reads a section header there: a panic)."""
    e57 = pye57.E57(str(tmp_path / "a.e57"), mode="w")
    imf = e57.image_file
    for name in ("{empty-1}", "{empty-2}"):
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, name))
        prototype = libe57.StructureNode(imf)
        for axis in "XYZ":
            prototype.set(f"cartesian{axis}", libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
        scan.set("points", libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True)))
        e57.data3d.append(scan)
    e57.close()
    with pytest.raises(PointCloudFormatError, match=r"none of the E57 file's 2 scan\(s\) declares a point") as caught:
        read_cloud(tmp_path / "a.e57")
    assert caught.value.status == 422
    data = (tmp_path / "a.e57").read_bytes()
    xml = xml_of(data).replace(b'recordCount="0"', b'recordCount="5"', 1)  # the first scan now declares points
    with pytest.raises(PointCloudFormatError, match=r"E57 scan 1 holds no points \(its recordCount is 0\)") as caught:
        read_cloud(with_xml(data, xml), "a.e57")
    assert caught.value.status == 400


def test_an_e57_declaring_more_points_than_memory_holds_is_a_400_without_a_limit(tmp_path) -> None:
    """The library reserves its arrays from the first scan's record count before it reads a point, and aborts the
    process where that allocation fails (a declared 2,000,000,000 points: 48 GB, SIGABRT); without a point limit (the
    CLI) the count is checked against the memory first."""
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}])
    data = (tmp_path / "a.e57").read_bytes()
    huge = with_xml(data, xml_of(data).replace(b'recordCount="%d"' % len(SOURCE), b'recordCount="%d"' % 10**15))
    with pytest.raises(PointCloudFormatError, match=r"declare 1000000000000000 points; reading them takes") as caught:
        read_cloud(huge, "a.e57")
    assert caught.value.status == 400 and "more than half of this machine's memory" in str(caught.value)


# ------------------------------------------------------------------------------------------------------ PTS / PTX


def test_pts_blocks_are_read_and_their_counts_checked() -> None:
    text = pts_text(SOURCE[:5]) + pts_text(SOURCE[5:8])
    np.testing.assert_array_equal(read_cloud(text.encode(), "a.pts"), SOURCE[:8])
    with pytest.raises(PointCloudFormatError, match=r"a\.pts: PTS line 1 declares 6 points; 5 rows follow") as short:
        read_cloud(("6" + pts_text(SOURCE[:5])[1:]).encode(), "a.pts")
    assert short.value.status == 400
    with pytest.raises(PointCloudFormatError, match="PTS line 1 declares 4 points; more rows follow them"):
        read_cloud(("4" + pts_text(SOURCE[:5])[1:]).encode(), "a.pts")


def test_pts_point_limit_comes_from_the_count_line() -> None:
    with pytest.raises(TooManyPointsError, match=r"a\.pts: has 1000000000 points; the limit is 400"):
        read_cloud(("1000000000" + pts_text(SOURCE[:5])[1:]).encode(), "a.pts", max_points=400)


def test_ptx_applies_the_row_vector_transform_and_leaves_out_missing_returns() -> None:
    # LAStools' sample PTX; CloudCompare and LAStools read its first point as 2.156 10.553 2.685
    matrix = np.array(
        [
            [-0.955179, 0.296021, -0.002106, 0],
            [-0.296023, -0.955180, 0.001152, 0],
            [-0.001670, 0.001724, 0.999997, 0],
            [3.847211, 12.235314, -0.425777, 1],
        ]
    )
    scanner = np.array([[1.111111, 2.111111, 3.111], [0, 0, 0], [1.333333, 2.333333, 3.333], [0, 0, 0]])
    xyz = read_cloud(ptx_text(scanner, matrix, columns=2).encode(), "a.ptx")
    np.testing.assert_allclose(xyz, scanner[[0, 2]] @ matrix[:3, :3] + matrix[3, :3])
    np.testing.assert_allclose(xyz[0], [2.156, 10.553, 2.685], atol=1e-3)


def test_ptx_scans_follow_each_other_each_with_its_transform() -> None:
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_z(30).T  # row-vector layout of a 30 degree turn
    matrix[3, :3] = [5.0, 6.0, 7.0]
    text = ptx_text(SOURCE[:20], np.eye(4), columns=4) + ptx_text(SOURCE[20:50], matrix, columns=5)
    xyz = read_cloud(text.encode(), "two.ptx")
    np.testing.assert_allclose(xyz, np.vstack([SOURCE[:20], SOURCE[20:50] @ rotation_z(30).T + [5, 6, 7]]))


def test_ptx_with_a_short_header_or_missing_rows_is_a_400() -> None:
    full = ptx_text(SOURCE[:6], np.eye(4), columns=3)
    lines = full.splitlines()
    with pytest.raises(PointCloudFormatError, match=r"a.ptx: PTX scan 1 \(line 1\) header line 6: expected 3 numbers"):
        read_cloud("\n".join(lines[:3] + lines[4:]).encode(), "a.ptx")  # the scanner's X axis left out
    with pytest.raises(PointCloudFormatError, match=r"the header of 10 lines .* ends at line 8"):
        read_cloud("\n".join(lines[:8]).encode(), "a.ptx")
    with pytest.raises(PointCloudFormatError, match=r"declares 3 x 2 = 6 points; 5 rows follow its header"):
        read_cloud("\n".join(full.splitlines()[:-1]).encode(), "a.ptx")


def test_sequence_frames_take_the_new_extensions(tmp_path) -> None:
    for suffix in (".e57", ".pts", ".ptx"):
        (tmp_path / f"f{suffix}").write_text("x")
        assert frame_problem(tmp_path / f"f{suffix}") is None


# ------------------------------------------------------------------------------------------------------------ HTTP


def upload(client, files: dict[str, tuple[str, bytes]]):
    return client.post("/v1/register", files=files, data=OPTIONS, timeout=120)


def test_e57_pts_and_ptx_uploads_give_the_npy_pose(client, tmp_path) -> None:
    def npy(xyz):
        np.save(tmp_path / "c.npy", xyz)
        return (tmp_path / "c.npy").read_bytes()

    def e57(xyz):
        write_e57(tmp_path / "c.e57", [{"xyz": xyz}])
        return (tmp_path / "c.e57").read_bytes()

    def pts(xyz):
        return pts_text(xyz).encode()

    def ptx(xyz):
        return ptx_text(xyz[: len(xyz) // 10 * 10], np.eye(4), columns=10).encode()

    source, target = SOURCE[:690], TARGET[:690]
    records = {}
    for name, encode in {"npy": npy, "e57": e57, "pts": pts, "ptx": ptx}.items():
        response = upload(client, {"source": (f"s.{name}", encode(source)), "target": (f"t.{name}", encode(target))})
        assert response.status_code == 200, (name, response.text)
        records[name] = response.json()
    for name in ("e57", "pts", "ptx"):
        np.testing.assert_allclose(records[name]["rotation"], records["npy"]["rotation"], atol=1e-6)
        np.testing.assert_allclose(records[name]["translation"], records["npy"]["translation"], atol=1e-6)


def test_damaged_tls_uploads_are_4xx_naming_the_file(client, tmp_path) -> None:
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}])
    good = ("t.pts", pts_text(TARGET).encode())
    cases = {
        ("cut.e57", (tmp_path / "a.e57").read_bytes()[:3000]): (400, "cut.e57", "E57 file is cut short"),
        ("count.pts", ("9" + pts_text(SOURCE[:5])[1:]).encode()): (400, "count.pts", "declares 9 points; 5 rows"),
        ("short.ptx", b"3\n2\n0 0 0\n1 0 0\n"): (400, "short.ptx", "header of 10 lines"),
    }
    for (name, data), (status, *words) in cases.items():
        assert_error(upload(client, {"source": (name, data), "target": good}), status, *words)


def test_a_damaged_e57_upload_is_a_400_and_no_rust_panic_on_the_servers_stderr(server, client, tmp_path) -> None:
    """A byte changed in a scan's points (its page's checksum no longer matches) made the e57 library panic: a 400
    still, but Rust's panic hook printed ``thread '<unnamed>' panicked at ...`` on the server's stderr, which reads as
    a crash in an operator's logs. The pages' checksums are checked before the library reads the file."""
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}])
    data = bytearray((tmp_path / "a.e57").read_bytes())
    data[100] ^= 0xFF  # page 0: the first scan's points
    response = upload(client, {"source": ("bad.e57", bytes(data)), "target": ("t.pts", pts_text(TARGET).encode())})
    assert response.status_code == 400, response.text
    log = server.log_path.read_text(errors="replace")  # the server subprocess's stdout and stderr
    assert "panicked" not in log and "RUST_BACKTRACE" not in log, log[-2000:]
    assert_error(response, 400, "bad.e57", "invalid checksum for page 0", "damaged")


def points_at(data: bytes, offset: int) -> bytes:
    """The E57 file ``data`` with its first scan's ``points`` ``fileOffset`` set to ``offset`` (pages rebuilt)."""
    xml = xml_of(data)
    start = xml.index(b'fileOffset="') + len(b'fileOffset="')
    return with_xml(data, xml[:start] + str(offset).encode() + xml[xml.index(b'"', start) :])


@pytest.mark.parametrize(
    ("offset", "message"),
    [
        (10**6, "puts scan 0's points at byte 1000000, at or past the end of the file"),
        (1020, "puts scan 0's points at byte 1020, a page's checksum"),
        (100, "puts scan 0's points at byte 100, where there is no compressed-vector section (a first byte of"),
        (8, "E57 scan 0's section (at byte 8) puts its first data packet at byte"),  # the header: a 1, zeros, offsets
    ],
)
def test_an_e57_scan_whose_file_offset_leads_to_no_section_is_refused_before_the_library_panics(
    tmp_path, offset: int, message: str
) -> None:
    """A well-formed, checksummed XML section whose scan's ``fileOffset`` leads to no compressed-vector section: the
    e57 library panicked (its hook printed the panic on stderr). The section header and its first packet's type are
    checked first."""
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}, {"xyz": TARGET}])
    data = points_at((tmp_path / "a.e57").read_bytes(), offset)
    with pytest.raises(PointCloudFormatError, match=re.escape(message)) as caught:
        read_cloud(data, "a.e57")
    assert caught.value.status == 400 and "damaged" in str(caught.value)


def test_an_e57_file_offset_past_the_file_is_a_400_and_no_rust_panic_on_the_servers_stderr(
    server, client, tmp_path
) -> None:
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}])
    data = points_at((tmp_path / "a.e57").read_bytes(), 10**6)
    response = upload(client, {"source": ("far.e57", data), "target": ("t.pts", pts_text(TARGET).encode())})
    log = server.log_path.read_text(errors="replace")  # the server subprocess's stdout and stderr
    assert "panicked" not in log and "RUST_BACKTRACE" not in log, log[-2000:]
    assert_error(response, 400, "far.e57", "scan 0's points at byte 1000000", "at or past the end of the file")


def test_e57_record_counts_are_checked_against_what_each_section_holds(tmp_path, capfd) -> None:
    """The e57 library reads a scan's data packets until it has its ``recordCount`` records, and panicked on what
    follows the last one where the count is larger (its hook printed the panic on stderr). The packets' headers are
    walked first: on libE57Format's files of several scans, single and double floats, integers and scaled integers,
    each scan's count reads, and one more is refused naming the scan, its count and what its section holds."""
    rng = np.random.default_rng(7)
    counts = [300, 120, 45]
    colour = ("integer", 0, 255)
    scans = [
        {
            **{f"cartesian{axis}": ("single", rng.normal(size=counts[0])) for axis in "XYZ"},
            **{f"color{name}": (colour, rng.integers(0, 256, counts[0])) for name in ("Red", "Green", "Blue")},
            "intensity": ("single", rng.uniform(size=counts[0])),
        },
        {
            **{f"cartesian{axis}": ("double", rng.normal(size=counts[1])) for axis in "XYZ"},
            "cartesianInvalidState": (("integer", 0, 2), np.zeros(counts[1])),
        },
        {
            **{
                f"cartesian{axis}": (("scaled", -(10**5), 10**5, 1e-3), rng.uniform(-99, 99, counts[2]).round(3))
                for axis in "XYZ"
            },
            "intensity": (("integer", 0, 2047), rng.integers(0, 2048, counts[2])),
        },
    ]
    write_typed_e57(tmp_path / "a.e57", scans)
    data = (tmp_path / "a.e57").read_bytes()
    assert len(read_cloud(data, "a.e57")) == sum(counts)
    for scan, count in enumerate(counts):
        declares = rf"E57 scan {scan} declares {count + 1} records \(its recordCount\)"
        message = rf"{declares}, and its section \(at byte [0-9]+\) holds {count} before byte"
        with pytest.raises(PointCloudFormatError, match=message) as caught:
            read_cloud(with_record_count(data, scan, count + 1), "a.e57")
        assert caught.value.status == 400 and "does not describe the file (it is damaged)" in str(caught.value)
    assert "panicked" not in capfd.readouterr().err


def _no_precision(xml: bytes) -> bytes:
    return xml.replace(b' precision="single"', b"", 3)  # scan 0's single floats read as doubles: half as many


def _other_section(xml: bytes) -> bytes:
    first, second = re.findall(rb'fileOffset="[0-9]+"', xml)
    return xml.replace(first, second, 1)  # scan 0 at scan 1's section, of 100 records


def _one_more_field(xml: bytes) -> bytes:
    return xml.replace(b"</prototype>", b'<intensity type="Float" precision="single"/></prototype>', 1)


def _zero_bits(xml: bytes) -> bytes:
    constant = rb'<cartesian\1 type="Integer" minimum="0" maximum="0"/>'
    return re.sub(rb'<cartesian([XYZ]) type="Float"[^>]*>[^<]*</cartesian[XYZ]>', constant, xml, count=3)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            _no_precision,
            r"E57 scan 0 declares 700 records \(its recordCount\), and its section \(at byte 48\) holds 350 before",
        ),
        (
            _other_section,
            r"E57 scan 0 declares 700 records \(its recordCount\), and its section \(at byte [0-9]+\) holds 100 before",
        ),
        (
            _one_more_field,
            r"E57 scan 0's prototype has 4 field\(s\), and its section \(at byte 48\) has a data packet of 3 bytes",
        ),
        (
            _zero_bits,
            r"E57 scan 0's prototype has 3 field\(s\), each an integer whose minimum is its maximum \(0 bits a",
        ),
    ],
    ids=["precision left out", "another scan's section", "a field added", "every field 0 bits"],
)
def test_an_e57_prototype_its_packets_do_not_match_is_refused_before_the_library_panics(
    tmp_path, capfd, edit, message: str
) -> None:
    """A checksummed XML section whose scan's prototype does not describe its section: a single-precision field read
    as a double (half the records), another scan's smaller section, a field more than the packets' bytestreams. The
    library panicked on each (a Float without ``precision`` is a double to it); a prototype of integers whose minimum
    is their maximum (0 bits a record) made it fill records until its memory ran out. Refused first."""
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}, {"xyz": TARGET[:100]}])
    data = (tmp_path / "a.e57").read_bytes()
    with pytest.raises(PointCloudFormatError, match=message) as caught:
        read_cloud(with_xml(data, edit(xml_of(data))), "a.e57")
    assert caught.value.status == 400
    assert "panicked" not in capfd.readouterr().err


@pytest.mark.parametrize("field", ["intensity", "colorRed"])
def test_an_e57_intensity_or_colour_whose_minimum_is_above_its_maximum_is_refused(tmp_path, capfd, field: str) -> None:
    """The library scales intensity and colour by their Float limits, and panicked on a minimum above the maximum
    ("Found invalid range"); equal limits, or limits equal in single precision, still read."""
    xyz = SOURCE[:50]
    fields = {f"cartesian{axis}": ("single", xyz[:, k]) for k, axis in enumerate("XYZ")}
    write_typed_e57(tmp_path / "a.e57", [{**fields, field: ("single", np.linspace(0, 1, len(xyz)))}])
    data = (tmp_path / "a.e57").read_bytes()
    element = rb"<%s type=\"Float\"[^>]*?(/>|>[^<]*</%s>)" % (field.encode(), field.encode())

    def limits(low: bytes, high: bytes) -> bytes:
        new = b'<%s type="Float" precision="single" minimum="%s" maximum="%s"/>' % (field.encode(), low, high)
        return with_xml(data, re.sub(element, new, xml_of(data), count=1))

    with pytest.raises(
        PointCloudFormatError, match=rf"gives scan 0's field '{field}' the minimum '7', above its"
    ) as caught:
        read_cloud(limits(b"7", b"1"), "a.e57")
    assert caught.value.status == 400
    assert "panicked" not in capfd.readouterr().err
    for low in (b"1", b"1.00000001"):  # 1.00000001 is 1 in single precision
        np.testing.assert_allclose(read_cloud(limits(low, b"1"), "a.e57"), xyz)


def test_an_e57_section_off_a_4_byte_boundary_reads_as_the_library_reads_it(tmp_path, capfd) -> None:
    """The library reads a data packet's bytestreams, then goes on at the next multiple of 4 bytes in the file. Where a
    section begins 2 bytes past one, that is 2 bytes past where the packet's own length (72) ends, and the library
    skips the 2 bytes between. A section of two such packets of 5 records each: the library reads its 10 records,
    and so does ``read_cloud`` (the walk of its packets took the bytes skipped for the next packet's header, and
    refused the file as damaged)."""
    e57 = pytest.importorskip("e57")
    xyz = SOURCE[:10]
    write_e57(tmp_path / "a.e57", [{"xyz": xyz}])
    xml = xml_of((tmp_path / "a.e57").read_bytes()).replace(b'fileOffset="48"', b'fileOffset="50"')
    streams = [xyz[:, k].astype("<f4").tobytes() for k in range(3)]
    header = struct.pack("<BBHH3H", 1, 0, 72 - 1, 3, 20, 20, 20)  # 12 + 60 bytes: a length of 72
    first, second = (header + b"".join(stream[half] for stream in streams) for half in (slice(0, 20), slice(20, 40)))
    # at byte 50 (2 past a multiple of 4): the section's header; its first packet at byte 82, 2 bytes skipped to the
    # second at byte 156, and 2 more to make the section's length whole 4-byte words
    packets = first + b"\xaa\xaa" + second + b"\xaa\xaa"
    section = struct.pack("<B7xQQQ", 1, 32 + len(packets), 82, 0) + packets
    logical = bytearray(48) + b"\0\0" + section
    xml_offset = len(logical)
    logical += xml
    HEADER.pack_into(logical, 0, b"ASTM-E57", 1, 0, -(-len(logical) // 1020) * 1024, xml_offset, len(xml), 1024)
    data = _paged(bytes(logical))
    (tmp_path / "b.e57").write_bytes(data)
    assert len(e57.read_points(str(tmp_path / "b.e57")).points) == len(xyz)  # the library reads it
    np.testing.assert_allclose(read_cloud(data, "b.e57"), xyz)
    assert "panicked" not in capfd.readouterr().err


@pytest.mark.parametrize(
    ("name", "kind", "found"),
    [
        ("cartesianInvalidState", ("integer", 0, 3), "the bounds 0 to 3"),
        ("cartesianInvalidState", ("integer", -1, 2), "the bounds -1 to 2"),
        ("sphericalInvalidState", ("integer", 0, 3), "the bounds 0 to 3"),
        ("cartesianInvalidState", "single", "the type 'Float'"),
    ],
)
def test_an_e57_invalid_state_other_than_an_integer_of_0_to_2_is_refused_before_the_library_panics(
    tmp_path, capfd, name: str, kind, found: str
) -> None:
    """The standard's ``cartesianInvalidState`` and ``sphericalInvalidState`` are Integers of 0 to 2; the e57 library
    panicked on a value outside them ("Cartesian invalid state contains invalid value: 3", its hook printing the panic
    on stderr), which wider bounds or a Float let a file hold. Refused from the XML section, naming the field; the
    standard's bounds, and narrower ones, still read."""
    xyz = SOURCE[:20]
    fields = {f"cartesian{axis}": ("single", xyz[:, k]) for k, axis in enumerate("XYZ")}
    if name == "sphericalInvalidState":  # the library reads it in a scan of spherical coordinates
        rae = np.column_stack([np.linalg.norm(xyz, axis=1), np.arctan2(xyz[:, 1], xyz[:, 0]), np.zeros(len(xyz))])
        fields = {f"spherical{axis}": ("double", rae[:, k]) for k, axis in enumerate(("Range", "Azimuth", "Elevation"))}
    state = np.r_[np.zeros(len(xyz) - 1), -1 if kind == ("integer", -1, 2) else 3]  # the last point's: outside 0-2
    write_typed_e57(tmp_path / "a.e57", [{**fields, name: (kind, state)}])
    data = (tmp_path / "a.e57").read_bytes()
    message = rf"gives scan 0's field '{name}' {re.escape(found)}; the standard's is an Integer of 0 to 2"
    with pytest.raises(PointCloudFormatError, match=message) as caught:
        read_cloud(data, "a.e57")
    assert caught.value.status == 400
    assert "panicked" not in capfd.readouterr().err
    cartesian = {f"cartesian{axis}": ("single", xyz[:, k]) for k, axis in enumerate("XYZ")}
    for bounds, read in (((0, 2), 19), ((0, 1), 19), ((0, 0), 20)):  # the last point: no return (2, 1), or kept
        state = np.r_[np.zeros(len(xyz) - 1), bounds[1]]
        write_typed_e57(tmp_path / "b.e57", [{**cartesian, "cartesianInvalidState": (("integer", *bounds), state)}])
        np.testing.assert_allclose(read_cloud(tmp_path / "b.e57"), xyz[:read])


@pytest.mark.parametrize("kind", ["index", "ignored"])
def test_an_e57_packet_other_than_data_among_a_scans_packets_is_refused_before_the_library_panics(
    tmp_path, capfd, kind: str
) -> None:
    """A section of two data packets of 5 records each with an index or ignored packet between them: the e57 library
    read the first 5 records, then panicked ("Cannot read next point because of logic error", its hook printing the
    panic on stderr). Refused from the packets' walk, naming the packet; the same section without it reads."""
    xyz = SOURCE[:10]
    write_e57(tmp_path / "a.e57", [{"xyz": xyz}])
    xml = xml_of((tmp_path / "a.e57").read_bytes())
    streams = [xyz[:, k].astype("<f4").tobytes() for k in range(3)]
    header = struct.pack("<BBHH3H", 1, 0, 72 - 1, 3, 20, 20, 20)  # 12 + 60 bytes: a length of 72
    first, second = (header + b"".join(stream[half] for stream in streams) for half in (slice(0, 20), slice(20, 40)))
    # an index packet: type 0, a reserved byte, length - 1, entry count, index level, 9 reserved bytes (16 bytes); an
    # ignored packet: type 2, a reserved byte, length - 1, and 4 bytes of its own
    other = struct.pack("<BBHHB9x", 0, 0, 15, 0, 0) if kind == "index" else struct.pack("<BBH4x", 2, 0, 7)

    def section(middle: bytes) -> bytes:
        packets = first + middle + second
        logical = bytearray(48) + struct.pack("<B7xQQQ", 1, 32 + len(packets), 80, 0) + packets
        xml_offset = len(logical)  # within the first page: its physical offset too
        logical += xml
        HEADER.pack_into(logical, 0, b"ASTM-E57", 1, 0, -(-len(logical) // 1020) * 1024, xml_offset, len(xml), 1024)
        return _paged(bytes(logical))

    np.testing.assert_allclose(read_cloud(section(b""), "a.e57"), xyz)
    holds = (
        r"E57 scan 0 declares 10 records \(its recordCount\), and its section \(at byte 48\) holds 5 before byte 152"
    )
    message = rf"{holds}, where an {kind} packet follows among its data packets: the e57 reader cannot read"
    with pytest.raises(PointCloudFormatError, match=message) as caught:
        read_cloud(section(other), "a.e57")
    assert caught.value.status == 400
    assert "panicked" not in capfd.readouterr().err


def test_an_e57_record_count_beyond_its_section_is_a_400_and_no_rust_panic_on_the_servers_stderr(
    server, client, tmp_path
) -> None:
    write_e57(tmp_path / "a.e57", [{"xyz": SOURCE}])
    data = with_record_count((tmp_path / "a.e57").read_bytes(), 0, len(SOURCE) + 1)
    response = upload(client, {"source": ("more.e57", data), "target": ("t.pts", pts_text(TARGET).encode())})
    log = server.log_path.read_text(errors="replace")  # the server subprocess's stdout and stderr
    assert "panicked" not in log and "RUST_BACKTRACE" not in log, log[-2000:]
    assert_error(response, 400, "more.e57", "E57 scan 0 declares 701 records (its recordCount)", "holds 700 before")


def test_e57_over_the_file_point_limit_is_a_413_from_its_header(tmp_path) -> None:
    server = limited_server()
    count = LIMITED["max_file_points"] + 1
    write_e57(tmp_path / "big.e57", [{"xyz": SOURCE[:300]}, {"xyz": TARGET[: count - 300]}])
    write_e57(tmp_path / "small.e57", [{"xyz": TARGET[:300]}])
    files = {
        "source": ("big.e57", (tmp_path / "big.e57").read_bytes()),
        "target": ("small.e57", (tmp_path / "small.e57").read_bytes()),
    }
    with server.client(headers={"Authorization": f"Bearer {LIMITED['api_key']}"}) as client:
        response = upload(client, files)
    assert_error(response, 413, "big.e57", str(count), str(LIMITED["max_file_points"]))
