"""Specification of the aligned cloud of a text source as the user's own file, moved (``write_moved``,
``mfgnet register --write-aligned``, ``mfgnet sequence --write-aligned``, ``POST /v1/register/aligned``): an
XYZ/CSV/TXT, PTS or PTX file keeps every line and every character but the numbers that place a point; rows keep their
order, colours, intensities, quotes, separators and line endings; x, y, z become ``R @ p + t`` with the decimals the
source's coordinates carry, named normals are rotated; a PTX scan's rows are copied and its header composed with the
pose. Each file is read back with the service's own reader."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from aligned_runs import pose, post_aligned, register, sequence
from api_server import assert_error
from cli_support import synthetic_pair
from scipy.spatial.transform import Rotation

from service.formats import PointCloudFormatError
from service.formats.moved import write_moved
from service.pointcloud_io import read_points

R = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True).as_matrix()
T = np.array([1.5, -2.0, 0.3])
RNG = np.random.default_rng(21)
XYZ = RNG.uniform(-20, 20, (300, 3))  # [300, 3]
RGB = RNG.integers(0, 256, (300, 3))  # [300, 3]
NORMALS = Rotation.random(300, random_state=3).apply([0.0, 0.0, 1.0])  # [300, 3] unit


def moved(xyz: np.ndarray, rotation: np.ndarray = R, translation: np.ndarray = T) -> np.ndarray:
    return np.asarray(xyz, dtype=np.float64) @ rotation.T + translation


def write(source: Path, out: Path, rotation: np.ndarray = R, translation: np.ndarray = T) -> None:
    largest = float(np.abs(moved(read_points(source), rotation, translation)).max())
    write_moved(source, out, rotation, translation, largest)


def decimals(token: str) -> int:
    return len(token.partition(".")[2])


def assert_rows(source: str, out: str, separator: str | None, columns: tuple[int, ...], expected: np.ndarray) -> None:
    """``out`` has ``source``'s lines; in its rows (``expected [n, k]`` of them, in order: the lines whose values in
    ``columns`` are numbers) the values of ``columns`` are ``expected`` to half a unit of their last decimal, with
    as many decimals as the most a source value of their group (x, y, z; normals) has, quoted as they were; every
    other value, the spacing and the line endings are the source's."""
    before, after = source.splitlines(keepends=True), out.splitlines(keepends=True)
    assert len(after) == len(before)
    is_row = [all(row_values(line, separator, c) is not None for c in columns) for line in before]
    groups = (columns[:3], columns[3:])
    places = {c: max(decimals(row_values(line, separator, c)) for line, r in zip(before, is_row, strict=True) if r)
              for group in groups for c in group}  # fmt: skip
    places = {c: max(places[g] for g in group) for group in groups for c in group}
    row = 0
    for old, new, old_is_row in zip(before, after, is_row, strict=True):
        if not old_is_row:
            assert new == old
            continue
        assert new[len(new.rstrip("\r\n")) :] == old[len(old.rstrip("\r\n")) :]  # the line ending kept
        if separator is None:
            assert re.findall(r"\s+", new) == re.findall(r"\s+", old)  # the spacing kept
        old_values, new_values = old.rstrip("\r\n").split(separator), new.rstrip("\r\n").split(separator)
        assert len(new_values) == len(old_values)
        for k, (a, b) in enumerate(zip(old_values, new_values, strict=True)):
            if k not in columns:
                assert b == a, (row, k)
        for c, column in enumerate(columns):
            a, b = old_values[column], new_values[column]
            assert (a.startswith('"'), a.endswith('"')) == (b.startswith('"'), b.endswith('"'))
            assert decimals(b.strip('"')) == places[column], (a, b)
            assert float(b.strip('"')) == pytest.approx(expected[row, c], abs=0.5 * 10.0 ** -places[column] + 1e-9)
        row += 1
    assert row == len(expected)


def row_values(line: str, separator: str | None, column: int) -> str | None:
    """The text of value ``column`` of ``line`` where it is a number (quotes taken off), else ``None``."""
    values = line.rstrip("\r\n").split(separator)
    try:
        float(values[column].strip('"'))
    except (IndexError, ValueError):
        return None
    return values[column].strip('"')


def pandas_csv(path: Path, quote_all: bool = False) -> str:
    """What ``DataFrame({"x":…, "y":…, "z":…, "red":…, …}).to_csv(path)`` writes: the index first under an empty
    name, floats as ``repr`` writes them; every value in double quotes with ``quoting=csv.QUOTE_ALL``."""
    q = '"' if quote_all else ""
    lines = [",".join(f"{q}{name}{q}" for name in ("", "x", "y", "z", "red", "green", "blue")) + "\n"]
    for index, (p, c) in enumerate(zip(np.round(XYZ, 6), RGB, strict=True)):
        lines.append(",".join(f"{q}{v}{q}" for v in (index, *map(repr, p.tolist()), *c.tolist())) + "\n")
    text = "".join(lines)
    path.write_text(text)
    return text


# ---------------------------------------------------------------------------------------------- XYZ/CSV/TXT


@pytest.mark.parametrize("quote_all", [False, True], ids=["pandas", "pandas-quote-all"])
def test_a_pandas_csv_keeps_its_index_colours_and_quotes_and_moves_x_y_z(tmp_path, quote_all) -> None:
    source, out = tmp_path / "scan.csv", tmp_path / "aligned.csv"
    text = pandas_csv(source, quote_all)
    write(source, out)
    assert_rows(text, out.read_text(), ",", (1, 2, 3), moved(read_points(source)))
    assert out.read_text().splitlines()[0] == text.splitlines()[0]  # the header line
    np.testing.assert_allclose(read_points(out), moved(read_points(source)), rtol=0, atol=0.5e-6 + 1e-9)


def test_a_whitespace_xyz_without_header_keeps_its_intensity_comments_spacing_and_crlf(tmp_path) -> None:
    source, out = tmp_path / "scan.xyz", tmp_path / "aligned.xyz"
    rows = [f"{x:.4f}\t{y:.4f}  {z:.4f} {i}\r\n" for (x, y, z), i in zip(XYZ, RGB[:, 0], strict=True)]
    text = "# scanner A, 2 returns\r\n" + "".join(rows[:100]) + "\r\n" + "".join(rows[100:]) + "# end\r\n"
    source.write_bytes(text.encode())
    write(source, out)
    written = out.read_bytes().decode()
    assert written.count("\r\n") == text.count("\r\n") and "\r\r" not in written
    assert_rows(text, written, None, (0, 1, 2), moved(read_points(source)))
    assert [line.split()[3] for line in written.splitlines() if line and line[0] != "#"] == [str(i) for i in RGB[:, 0]]
    np.testing.assert_allclose(read_points(out), moved(read_points(source)), rtol=0, atol=0.5e-4 + 1e-9)


def test_a_file_without_header_whose_rows_end_in_labels_has_its_first_row_moved_too(tmp_path) -> None:
    source, out = tmp_path / "labelled.xyz", tmp_path / "aligned.xyz"
    text = "".join(f"{x:.4f} {y:.4f} {z:.4f} class_{i % 3}\n" for i, (x, y, z) in enumerate(XYZ))
    source.write_text(text)
    write(source, out)
    assert len(read_points(source)) == len(XYZ)  # the first row was taken for a header and left where it was
    assert_rows(text, out.read_text(), None, (0, 1, 2), moved(read_points(source)))
    np.testing.assert_allclose(read_points(out), moved(read_points(source)), rtol=0, atol=0.5e-4 + 1e-9)


def test_columns_named_in_a_numpy_savetxt_comment_are_the_ones_moved(tmp_path) -> None:
    source, out = tmp_path / "scan.txt", tmp_path / "aligned.txt"
    np.savetxt(source, np.column_stack([RGB[:, 0], XYZ]), fmt="%.6f", header="intensity x y z")
    write(source, out)
    moved_rows = np.loadtxt(out)  # [N, 4]
    np.testing.assert_array_equal(moved_rows[:, 0], RGB[:, 0])
    np.testing.assert_allclose(moved_rows[:, 1:], moved(read_points(source)), rtol=0, atol=0.5e-6 + 1e-9)


def test_named_normals_are_rotated_and_other_columns_kept(tmp_path) -> None:
    """CloudCompare's header (``//X Y Z R G B Nx Ny Nz``): the normals turn with the points, colours stay."""
    source, out = tmp_path / "scan.txt", tmp_path / "aligned.txt"
    rows = [
        " ".join([*(f"{v:.6f}" for v in p), *map(str, c), *(f"{v:.6f}" for v in n)])
        for p, c, n in zip(XYZ, RGB, NORMALS, strict=True)
    ]
    text = "//X Y Z R G B Nx Ny Nz\n" + "\n".join(rows) + "\n"
    source.write_text(text)
    write(source, out)
    expected = np.column_stack([moved(read_points(source)), np.round(NORMALS, 6) @ R.T])  # [n, 6]
    assert_rows(text, out.read_text(), None, (0, 1, 2, 6, 7, 8), expected)


def test_the_decimals_of_the_coordinates_are_kept_and_exponents_counted(tmp_path) -> None:
    """``%.2f`` stays ``%.2f`` (no 17-digit noise); ``1.5e-04`` carries 5 decimals; a file of float64 ``repr``s
    (more than 15 decimals) gets each moved value's shortest float64 text."""
    cases = {
        "cm.xyz": ("\n".join(" ".join(f"{v:.2f}" for v in p) for p in XYZ[:5]) + "\n", 2),
        "exp.xyz": ("1.5e-04 2.0 3.0\n1.0 2.0 3.0\n", 5),
    }
    for name, (text, places) in cases.items():
        (tmp_path / name).write_text(text)
        write(tmp_path / name, tmp_path / f"out_{name}")
        for line in (tmp_path / f"out_{name}").read_text().splitlines():
            assert [decimals(v) for v in line.split()] == [places] * 3, (name, line)
    full = tmp_path / "full.xyz"
    full.write_text("\n".join(" ".join(map(repr, p.tolist())) for p in XYZ[:5] / 7) + "\n")
    write(full, tmp_path / "out_full.xyz")
    values = np.array([[float(v) for v in line.split()] for line in (tmp_path / "out_full.xyz").read_text().split("\n")
                       if line])  # fmt: skip
    np.testing.assert_array_equal(values, moved(XYZ[:5] / 7))  # read back exactly as computed


def test_whole_numbers_get_four_significant_digits_and_normals_six_decimals(tmp_path) -> None:
    """A file of whole numbers (a hand-made cloud in metres) is not rounded to whole metres once turned: its largest
    coordinate (here 1-2 digits) keeps 4 significant digits; whole-number normals (``0 0 1``) get 6 decimals."""
    whole = np.round(XYZ[:20]).astype(int)  # [20, 3], |v| <= 20
    source = tmp_path / "whole.xyz"
    source.write_text("x y z nx ny nz\n" + "".join(" ".join(map(str, [*p, 0, 0, 1])) + "\n" for p in whole))
    write(source, tmp_path / "out.xyz")
    rows = [line.split() for line in (tmp_path / "out.xyz").read_text().splitlines()[1:]]
    assert {decimals(v) for row in rows for v in row[:3]} == {2}
    assert {decimals(v) for row in rows for v in row[3:]} == {6}
    values = np.array(rows, dtype=np.float64)  # [20, 6]
    np.testing.assert_allclose(values[:, :3], moved(whole), atol=0.005 + 1e-9)
    np.testing.assert_allclose(values[:, 3:], np.tile(R[:, 2], (20, 1)), atol=5e-7 + 1e-12)


def test_an_output_naming_its_source_is_written_from_the_whole_source(tmp_path) -> None:
    source = tmp_path / "scan.csv"
    text = pandas_csv(source)
    before = read_points(source)
    write(source, source)
    assert_rows(text, source.read_text(), ",", (1, 2, 3), moved(before))
    assert [p.name for p in tmp_path.iterdir()] == ["scan.csv"]  # no temporary file left


@pytest.mark.parametrize("row", [b"4.0 five 6.0\n", b"4.0 \xff 6.0\n"], ids=["word", "not-utf-8"])
def test_a_row_changed_since_it_was_read_is_an_error_and_leaves_no_file(tmp_path, row) -> None:
    source, out = tmp_path / "scan.xyz", tmp_path / "aligned.xyz"
    source.write_bytes(b"1.0 2.0 3.0\n" * 200 + row)  # the change past the bytes the format is found from
    with pytest.raises(PointCloudFormatError, match="changed since it was read"):
        write_moved(source, out, R, T, 10.0)
    assert [p.name for p in tmp_path.iterdir()] == ["scan.xyz"]


def test_the_file_is_moved_the_same_whatever_the_chunk_boundaries(tmp_path, monkeypatch) -> None:
    """Rows are moved a chunk of lines at a time (memory bounded for millions of rows): a chunk boundary inside a
    PTS block, between comment lines or before a quoted row changes nothing."""
    files = {"scan.csv": pandas_csv(tmp_path / "scan.csv", quote_all=True)}
    (tmp_path / "mixed.csv").write_text(files["scan.csv"].replace('"1"', "1", 3) + "# note\n\n")
    files["scan.pts"] = pts_text(tmp_path / "scan.pts")
    for name in ("scan.csv", "mixed.csv", "scan.pts"):
        write(tmp_path / name, tmp_path / f"whole_{name}")
    from service.formats import moved_text

    monkeypatch.setattr(moved_text, "CHUNK_CHARS", 100)
    for name in ("scan.csv", "mixed.csv", "scan.pts"):
        write(tmp_path / name, tmp_path / f"chunked_{name}")
        assert (tmp_path / f"chunked_{name}").read_bytes() == (tmp_path / f"whole_{name}").read_bytes(), name


# ----------------------------------------------------------------------------------------------------- PTS


def pts_text(path: Path) -> str:
    """Two blocks (Cyclone's layout): a count, then rows ``x y z intensity r g b``."""
    blocks = []
    for rows in (slice(0, 120), slice(120, 300)):
        lines = [f"{rows.stop - rows.start}"]
        lines += [
            f"{x:.3f} {y:.3f} {z:.3f} {i} {r} {g} {b}"
            for (x, y, z), i, (r, g, b) in zip(XYZ[rows], -RGB[rows, 0], RGB[rows], strict=True)
        ]
        blocks.append("\n".join(lines) + "\n")
    text = "".join(blocks)
    path.write_text(text)
    return text


def test_a_pts_file_keeps_its_blocks_intensities_and_colours(tmp_path) -> None:
    source, out = tmp_path / "scan.pts", tmp_path / "aligned.pts"
    text = pts_text(source)
    write(source, out)
    written = out.read_text()
    assert [line for line in written.splitlines() if " " not in line] == ["120", "180"]  # the count lines
    assert_rows(text, written, None, (0, 1, 2), moved(read_points(source)))
    np.testing.assert_allclose(read_points(out), moved(read_points(source)), rtol=0, atol=0.5e-3 + 1e-9)


# ----------------------------------------------------------------------------------------------------- PTX


def ptx_scan(turn: Rotation, at: np.ndarray, grid: np.ndarray, decimals: int = 6) -> str:
    """A PTX scan of ``grid [columns * rows, 3]`` points in the scanner's frame, registered by ``turn`` and ``at`` as
    Cyclone writes it: position, axes (the rows of the rotation) and the 4x4 in the row-vector convention."""
    rotation = turn.as_matrix()  # p_registered = rotation @ p + at
    f = f"{{:.{decimals}f}}".format
    header = ["4", str(len(grid) // 4), " ".join(map(f, at))]
    header += [" ".join(map(f, axis)) for axis in rotation.T]  # the scanner's axes in the registered frame
    header += [" ".join(map(f, axis)) + " 0" for axis in rotation.T] + [" ".join(map(f, at)) + " 1"]
    rows = [" ".join([*(f"{v:.4f}" for v in p), "0.5", "10", "20", "30"]) for p in grid]
    return "\n".join(header + rows) + "\n"


def ptx_file(path: Path) -> tuple[str, np.ndarray]:
    """Two scans of 4 x 5 directions, a few with no return (``0 0 0``), each with its own registration; returns the
    text and the registered points."""
    text, points = "", []
    for k, grid in enumerate((XYZ[:20].copy(), XYZ[20:40].copy())):
        grid[[3, 7, 11]] = 0.0  # no return
        turn = Rotation.from_euler("zyx", [40.0 * (k + 1), 3.0, -2.0], degrees=True)
        at = np.array([10.0 * k, -5.0, 1.5])
        scan = ptx_scan(turn, at, grid)
        text += scan
        header = np.array([[float(v) for v in line.split()] for line in scan.splitlines()[6:10]])  # [4, 4]
        kept = grid[(grid != 0).any(axis=1)]
        points.append(np.round(kept, 4) @ header[:3, :3] + header[3, :3])
    path.write_text(text)
    return text, np.concatenate(points)


def test_a_ptx_file_keeps_its_rows_and_composes_each_scans_header_with_the_pose(tmp_path) -> None:
    source, out = tmp_path / "scan.ptx", tmp_path / "aligned.ptx"
    text, registered = ptx_file(source)
    np.testing.assert_allclose(read_points(source), registered, atol=1e-9)
    write(source, out)
    before, after = text.splitlines(), out.read_text().splitlines()
    assert len(after) == len(before)
    for scan in (0, 30):  # each scan: 10 header lines, then 20 rows copied as they are (0 0 0 among them)
        assert after[scan : scan + 2] == before[scan : scan + 2]
        assert after[scan + 10 : scan + 30] == before[scan + 10 : scan + 30]
        old = [np.array([float(v) for v in line.split()]) for line in before[scan + 2 : scan + 10]]
        new = [np.array([float(v) for v in line.split()]) for line in after[scan + 2 : scan + 10]]
        np.testing.assert_allclose(new[0], R @ old[0] + T, atol=1e-12)  # the scanner's position, moved
        for axis in (1, 2, 3):
            np.testing.assert_allclose(new[axis], R @ old[axis], atol=1e-12)  # its axes, turned
        M, moved_M = np.array(old[4:]), np.array(new[4:])  # [4, 4] row-vector convention
        np.testing.assert_allclose(moved_M[:3, :3], M[:3, :3] @ R.T, atol=1e-12)
        np.testing.assert_allclose(moved_M[3, :3], R @ M[3, :3] + T, atol=1e-12)
        np.testing.assert_array_equal(moved_M[:, 3], M[:, 3])
    np.testing.assert_allclose(read_points(out), moved(registered), rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------------------ CLI


def test_register_writes_the_csv_and_the_ptx_moved(tmp_path, model_dir) -> None:
    source, _ = synthetic_pair()
    np.save(tmp_path / "target.npy", synthetic_pair()[1])
    csv_text = "x,y,z,red,green,blue\n" + "".join(
        f"{x:.5f},{y:.5f},{z:.5f},{k % 256},{k * 7 % 256},{k * 13 % 256}\n" for k, (x, y, z) in enumerate(source)
    )
    (tmp_path / "scan.csv").write_text(csv_text)
    out, aligned = tmp_path / "pose.json", tmp_path / "aligned.txt"
    result = register(tmp_path / "scan.csv", tmp_path / "target.npy", "--out", out, "--write-aligned", aligned,
                      model_dir=model_dir)  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "note" not in result.stderr
    rotation, translation = pose(out)
    expected = moved(read_points(tmp_path / "scan.csv"), rotation, translation)
    assert_rows(csv_text, aligned.read_text(), ",", (0, 1, 2), expected)

    text, registered = ptx_file(tmp_path / "scan.ptx")
    result = register(tmp_path / "scan.ptx", tmp_path / "target.npy", "--out", out, "--write-aligned",
                      tmp_path / "aligned.ptx", model_dir=model_dir)  # fmt: skip
    assert result.exit_code == 0, result.output
    rotation, translation = pose(out)
    written = (tmp_path / "aligned.ptx").read_text().splitlines()
    assert written[10:30] == text.splitlines()[10:30]  # the rows, as they were
    np.testing.assert_allclose(read_points(tmp_path / "aligned.ptx"), moved(registered, rotation, translation),
                               atol=1e-9)  # fmt: skip


def test_a_pts_or_ptx_output_of_another_format_is_a_usage_error_before_anything_is_read(tmp_path, model_dir) -> None:
    pandas_csv(tmp_path / "scan.csv")
    for suffix, name in ((".pts", "PTS"), (".ptx", "PTX")):
        aligned = tmp_path / f"aligned{suffix}"
        result = register(tmp_path / "scan.csv", tmp_path / "missing.npy", "--write-aligned", aligned,
                          model_dir=model_dir)  # fmt: skip
        assert result.exit_code == 2 and "Traceback" not in result.output
        assert f"a {name} file is written only from a {name} source" in result.stderr
        assert "scan.csv is XYZ/CSV/TXT" in result.stderr and not aligned.exists()


def test_sequence_keeps_pts_and_ptx_frames_in_their_own_format(tmp_path, model_dir) -> None:
    source, target = synthetic_pair()
    frames = [tmp_path / "f0.pts", tmp_path / "f1.ptx", tmp_path / "f2.xyz"]
    frames[0].write_text(f"{len(target)}\n" + "".join(f"{x:.6f} {y:.6f} {z:.6f} -7 1 2 3\n" for x, y, z in target))
    ptx = ptx_scan(Rotation.identity(), np.zeros(3), np.concatenate([source, np.zeros((4 - len(source) % 4, 3))]))
    frames[1].write_text(ptx)
    frames[2].write_text("".join(f"{x:.6f} {y:.6f} {z:.6f} 0.25\n" for x, y, z in source))
    folder, steps = tmp_path / "aligned", tmp_path / "steps.jsonl"
    folder.mkdir()
    result = sequence(frames, folder, model_dir, steps)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in folder.iterdir()) == ["f0.pts", "f1.ptx", "f2.xyz"]
    assert (folder / "f0.pts").read_text() == frames[0].read_text()  # frame 0: the identity
    accumulated = [np.asarray(json.loads(line)["accumulated_transform"]) for line in steps.read_text().splitlines()]
    for frame, T_0_i in zip(frames[1:], accumulated, strict=True):
        written = folder / frame.name
        expected = moved(read_points(frame), T_0_i[:3, :3], T_0_i[:3, 3])
        np.testing.assert_allclose(read_points(written), expected, rtol=0, atol=0.5e-6 + 1e-9)
        rows = 10 if frame.suffix == ".ptx" else 0  # the first row's line
        kept = [line.split()[3:] for line in written.read_text().splitlines()[rows:]]
        assert kept == [line.split()[3:] for line in frame.read_text().splitlines()[rows:]]  # intensity, colours


# ----------------------------------------------------------------------------------------------------- HTTP


def post(client, path: Path, name: str | None = None):
    return post_aligned(client, path, R, T, name)


def test_the_page_downloads_text_files_moved_in_their_own_format(client, tmp_path) -> None:
    pandas_csv(tmp_path / "scan.csv")
    pts_text(tmp_path / "scan.pts")
    ptx_file(tmp_path / "scan.ptx")
    cases = [("scan.csv", None, "scan_aligned.csv", "text/csv"), ("scan.csv", "scan.dat", "scan_aligned.txt",
             "text/plain"), ("scan.pts", None, "scan_aligned.pts", "text/plain"),
             ("scan.ptx", None, "scan_aligned.ptx", "text/plain")]  # fmt: skip
    for name, upload_name, download, media in cases:
        answer = post(client, tmp_path / name, upload_name)
        assert answer.status_code == 200, answer.text
        assert answer.headers["content-type"] == f"{media}; charset=utf-8"
        assert answer.headers["content-disposition"] == f'attachment; filename="{download}"'
        assert int(answer.headers["content-length"]) == len(answer.content)
        write(tmp_path / name, tmp_path / f"cli_{name}")
        assert answer.content == (tmp_path / f"cli_{name}").read_bytes()  # the CLI's file, byte for byte


def test_the_page_refuses_a_text_upload_it_cannot_read_before_writing_anything(client, tmp_path) -> None:
    (tmp_path / "bad.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    assert_error(post(client, tmp_path / "bad.csv"), 422, "bad.csv")
