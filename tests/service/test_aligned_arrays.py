"""Specification of the aligned cloud of an ``.npy`` or ``.npz`` source as the user's own array, moved
(``write_moved``, ``mfgnet register --write-aligned``, ``mfgnet sequence --write-aligned``,
``POST /v1/register/aligned``): the same shape, order and dtype (float32 widened to float64 only for map
coordinates, integers written as float64), the first three columns or the fields x, y, z moved by ``R @ p + t``, a
structured array's normals and an archive's ``normals`` array rotated, every other column, field and member kept
byte for byte, an archive's members in their order and compression. Each file is read back with numpy."""

from __future__ import annotations

import contextlib
import io
import json
import re
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from aligned_runs import pose, post_aligned, register, runner, sequence
from api_server import assert_error, free_port
from cli_support import synthetic_pair
from scipy.spatial.transform import Rotation

from service.cli import app
from service.formats import PointCloudFormatError
from service.formats.moved import check_moved, write_moved
from service.formats.moved_arrays import check_moved_npy, check_moved_npz
from service.pointcloud_io import read_points

R = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True).as_matrix()
T = np.array([1.5, -2.0, 0.3])
UTM = np.array([512_345.0, 4_123_456.0, 150.0])
RNG = np.random.default_rng(5)
N = 600  # as synthetic_pair's clouds
XYZ = RNG.uniform(-20, 20, (N, 3))  # [N, 3]
NORMALS = Rotation.random(N, random_state=3).apply([0.0, 0.0, 1.0])  # [N, 3] unit
COLOURS = RNG.integers(0, 256, (N, 3), dtype=np.uint8)  # [N, 3]
LABELS = RNG.integers(0, 40, N, dtype=np.int32)  # [N]


def moved(xyz: np.ndarray, rotation: np.ndarray = R, translation: np.ndarray = T) -> np.ndarray:
    return np.asarray(xyz, dtype=np.float64) @ rotation.T + translation


def write(source: Path, out: Path, rotation: np.ndarray = R, translation: np.ndarray = T) -> None:
    largest = float(np.abs(moved(read_points(source), rotation, translation)).max())
    write_moved(source, out, rotation, translation, largest=largest)


def assert_moved(values: np.ndarray, expected: np.ndarray) -> None:
    """``values`` are ``expected`` (float64) stored in ``values``' dtype: within one step of it."""
    step = np.spacing(np.abs(expected).max().astype(values.dtype))
    np.testing.assert_allclose(np.asarray(values, dtype=np.float64), expected, rtol=0, atol=float(step))


def header_bytes(path: Path) -> bytes:
    with open(path, "rb") as f:
        np.lib.format.read_magic(f)
        np.lib.format.read_array_header_1_0(f)
        return path.read_bytes()[: f.tell()]


def table(dtype: str) -> np.ndarray:
    """``[N, 6]``: x, y, z, then three columns (normals, which a plain array does not name)."""
    return np.concatenate([XYZ, NORMALS], axis=1).astype(dtype)


# ------------------------------------------------------------------------------------------------- .npy


@pytest.mark.parametrize("dtype", ["<f4", "<f8", ">f4"])
@pytest.mark.parametrize("layout", ["C", "F", "batch"])
def test_an_array_keeps_its_shape_order_dtype_and_other_columns(tmp_path, dtype, layout) -> None:
    array = table(dtype)
    if layout == "F":
        array = np.asfortranarray(array)
    elif layout == "batch":
        array = array[None]  # [1, N, 6]
    source, out = tmp_path / "cloud.npy", tmp_path / "aligned.npy"
    np.save(source, array)
    write(source, out)
    written = np.load(out)
    assert written.shape == array.shape and written.dtype == array.dtype
    assert written.flags.f_contiguous == (layout == "F") and header_bytes(out) == header_bytes(source)
    rows, kept = written.reshape(N, 6), array.reshape(N, 6)
    assert rows[:, 3:].tobytes() == kept[:, 3:].tobytes()  # a plain array's other columns are copied, never turned
    assert_moved(rows[:, :3], moved(kept[:, :3]))
    assert out.stat().st_size == source.stat().st_size


def test_a_float32_array_moved_into_map_coordinates_becomes_float64_with_its_other_values(tmp_path) -> None:
    source, out = tmp_path / "cloud.npy", tmp_path / "aligned.npy"
    np.save(source, table("<f4"))
    write(source, out, R, UTM)
    written = np.load(out)
    assert written.dtype == np.float64 and written.shape == (N, 6)
    np.testing.assert_array_equal(written[:, 3:], table("<f4")[:, 3:].astype(np.float64))
    np.testing.assert_allclose(written[:, :3], moved(table("<f4")[:, :3], R, UTM), rtol=0, atol=1e-9)


def test_an_integer_array_becomes_float64_its_labels_exactly_kept(tmp_path) -> None:
    array = np.concatenate([np.round(XYZ * 1000), LABELS[:, None]], axis=1).astype(np.int64)  # millimetres, label
    source, out = tmp_path / "grid.npy", tmp_path / "aligned.npy"
    np.save(source, array)
    write(source, out)
    written = np.load(out)
    assert written.dtype == np.float64 and written.shape == (N, 4)
    np.testing.assert_array_equal(written[:, 3], LABELS)
    assert_moved(written[:, :3], moved(array[:, :3]))
    array[7, 3] = 2**53 + 1  # float64 would round it
    np.save(source, array)
    with pytest.raises(PointCloudFormatError, match=r"beyond 2\*\*53"):
        write(source, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["aligned.npy", "grid.npy"]  # no temporary file left
    np.save(source, np.zeros((N, 40), dtype=np.int8))  # 40 bytes a row would be 320 as float64
    with pytest.raises(PointCloudFormatError, match="would be 320 bytes as float64: at most 256"):
        write(source, out)


@pytest.mark.parametrize("names", [("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z")])
def test_a_structured_array_rotates_its_normals_and_keeps_its_other_fields(tmp_path, names) -> None:
    fields = [(a, "<f4") for a in "xyz"] + [(n, "<f4") for n in names] + [("intensity", "<u2"), ("label", "<i4")]
    array = np.zeros(N, dtype=fields)
    for k in range(3):
        array["xyz"[k]], array[names[k]] = XYZ[:, k], NORMALS[:, k]
    array["intensity"], array["label"] = RNG.integers(0, 65535, N), LABELS
    source, out = tmp_path / "cloud.npy", tmp_path / "aligned.npy"
    np.save(source, array)
    write(source, out)
    written = np.load(out)
    assert written.dtype == array.dtype and header_bytes(out) == header_bytes(source)
    for name in ("intensity", "label"):
        assert written[name].tobytes() == array[name].tobytes(), name
    assert_moved(np.stack([written[a] for a in "xyz"], 1), moved(np.stack([array[a] for a in "xyz"], 1)))
    assert_moved(np.stack([written[n] for n in names], 1), moved(np.stack([array[n] for n in names], 1), R, 0))


@pytest.mark.parametrize(
    "dtype",
    [
        np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<i4")]),  # no normals
        np.dtype([("label", "u1"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("flag", "u1")], align=True),  # padded
        np.dtype({"names": ["x", "y", "z"], "formats": ["<f8"] * 3, "titles": ["east", "north", "up"]}),
        np.dtype([("x", np.longdouble), ("y", np.longdouble), ("z", np.longdouble), ("label", "<i4")]),
    ],
    ids=["no-normals", "padded", "titles", "longdouble"],
)
def test_a_structured_array_without_normals_keeps_its_dtype_byte_for_byte(tmp_path, dtype) -> None:
    """A record without normal fields (it was a ValueError, a traceback in the CLI and a 500 on the page); a record
    whose x, y, z are kept keeps its own dtype: its padding and titles, 16-byte floats not narrowed to 4 bytes."""
    array = np.zeros(N, dtype=dtype)
    for k in range(3):
        array["xyz"[k]] = XYZ[:, k]
    if "label" in dtype.names:
        array["label"] = LABELS
    source, out = tmp_path / "cloud.npy", tmp_path / "aligned.npy"
    np.save(source, array)
    write(source, out)
    written = np.load(out)
    assert written.dtype == array.dtype and header_bytes(out) == header_bytes(source)
    if "label" in dtype.names:
        assert written["label"].tobytes() == array["label"].tobytes()
    xyz = np.stack([array[a].astype(np.float64) for a in "xyz"], 1)
    assert_moved(np.stack([written[a] for a in "xyz"], 1), moved(xyz))


# ------------------------------------------------------------------------------------------------- .npz


def members(path: Path) -> list[tuple[str, int]]:
    with zipfile.ZipFile(path) as archive:
        return [(info.filename, info.compress_type) for info in archive.infolist()]


def member_bytes(path: Path, name: str) -> bytes:
    with zipfile.ZipFile(path) as archive:
        return archive.read(name)


@pytest.mark.parametrize("save", [np.savez, np.savez_compressed], ids=["stored", "deflated"])
def test_an_npz_keeps_every_other_array_in_its_order_and_compression(tmp_path, save) -> None:
    source, out = tmp_path / "scan.npz", tmp_path / "aligned.npz"
    save(source, colors=COLOURS, points=XYZ.astype(np.float32), labels=LABELS, scale=np.float64(0.25))
    write(source, out)
    assert members(out) == members(source)
    for name in ("colors.npy", "labels.npy", "scale.npy"):
        assert member_bytes(out, name) == member_bytes(source, name), name
    written = np.load(out)
    assert written["points"].dtype == np.float32
    assert_moved(written["points"], moved(XYZ.astype(np.float32)))


def test_an_npz_made_on_windows_keeps_the_system_its_attributes_are_read_by(tmp_path) -> None:
    """A member's attributes mean what the system that made it says (MS-DOS: 0; Unix: 3, a file mode in the high
    bits): the copy kept an MS-DOS member's attributes (0x20, archive) but was marked as made on Unix, which reads them
    as a mode of 0 (no permissions) when it is unzipped."""
    source, out = tmp_path / "windows.npz", tmp_path / "aligned.npz"
    with zipfile.ZipFile(source, "w") as archive:
        for name, array in (("points.npy", XYZ), ("labels.npy", LABELS)):
            info = zipfile.ZipInfo(name, (2024, 5, 1, 12, 0, 0))
            info.create_system, info.external_attr = 0, 0x20
            data = io.BytesIO()
            np.save(data, array)
            archive.writestr(info, data.getvalue())
    write(source, out)
    with zipfile.ZipFile(source) as before, zipfile.ZipFile(out) as after:
        made = [(info.filename, info.create_system, info.external_attr) for info in before.infolist()]
        assert [(info.filename, info.create_system, info.external_attr) for info in after.infolist()] == made
    assert_moved(np.load(out)["points"], moved(XYZ))


@pytest.mark.parametrize("key", ["positions", "points"])
def test_open3d_positions_and_their_normals_are_moved_and_rotated(tmp_path, key) -> None:
    """Open3D's ``o3d.t.io`` writes ``positions``, ``normals`` and ``colors`` (float32)."""
    source, out = tmp_path / "o3d.npz", tmp_path / "aligned.npz"
    colours = (COLOURS / 255).astype(np.float32)
    np.savez_compressed(source, **{key: XYZ.astype(np.float32)}, normals=NORMALS.astype(np.float32), colors=colours)
    write(source, out)
    written = np.load(out)
    assert_moved(written[key], moved(XYZ.astype(np.float32)))
    assert_moved(written["normals"], moved(NORMALS.astype(np.float32), R, 0))
    assert member_bytes(out, "colors.npy") == member_bytes(source, "colors.npy")


def test_normals_of_another_row_count_are_copied_as_they_are(tmp_path) -> None:
    source, out = tmp_path / "o3d.npz", tmp_path / "aligned.npz"
    np.savez(source, positions=XYZ, normals=NORMALS[:10])
    write(source, out)
    assert member_bytes(out, "normals.npy") == member_bytes(source, "normals.npy")


def test_an_npz_whose_other_arrays_expand_beyond_the_limit_is_refused_before_writing(tmp_path) -> None:
    """A deflated member of zeros is a few kilobytes that ask for as many megabytes of work as it declares."""
    source, out = tmp_path / "bomb.npz", tmp_path / "aligned.npz"
    np.savez_compressed(source, points=XYZ[:20], padding=np.zeros(1 << 19))  # 4 MiB of zeros
    assert source.stat().st_size < 100_000
    with pytest.raises(PointCloudFormatError, match="other arrays expand to"):
        write(source, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bomb.npz"]


def test_a_second_member_named_as_the_cloud_is_copied_within_the_other_members_limit(tmp_path) -> None:
    """Of two members named ``points.npy`` numpy reads the last: the other was moved too, however many rows its header
    declared (a deflated array of zeros asked for any amount of work and disk); it is now one of the other members."""
    source, out = tmp_path / "twice.npz", tmp_path / "aligned.npz"
    with zipfile.ZipFile(source, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for array in (np.zeros((200_000, 3)), XYZ):  # 4.8 MB of zeros, then the cloud numpy reads
            data = io.BytesIO()
            np.save(data, array)
            with pytest.warns(UserWarning, match="Duplicate name") if array is XYZ else contextlib.nullcontext():
                archive.writestr("points.npy", data.getvalue())
    assert source.stat().st_size < 100_000
    with pytest.raises(PointCloudFormatError, match="other arrays expand to 4800128 bytes"):
        write(source, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["twice.npz"]
    small = tmp_path / "small.npz"  # a small one: copied as it is, the last one moved
    with zipfile.ZipFile(small, "w") as archive:
        for array in (XYZ[:5], XYZ):
            data = io.BytesIO()
            np.save(data, array)
            with pytest.warns(UserWarning, match="Duplicate name") if array is XYZ else contextlib.nullcontext():
                archive.writestr("points.npy", data.getvalue())
    with pytest.warns(UserWarning, match="Duplicate name"):  # zipfile's, writing the copy of the first
        write(small, out)
    with zipfile.ZipFile(small) as before, zipfile.ZipFile(out) as after:
        first = [archive.open(archive.infolist()[0]).read() for archive in (before, after)]
        assert first[0] == first[1] and len(after.infolist()) == 2
    assert_moved(np.load(out)["points"], moved(XYZ))


# -------------------------------------------------------------------------------------------------- CLI


def test_register_writes_an_npy_and_an_npz_as_themselves_moved(tmp_path, model_dir) -> None:
    source, target = synthetic_pair()
    np.save(tmp_path / "target.npy", target)
    cloud = np.concatenate([source, NORMALS[: len(source)]], axis=1).astype(np.float32)  # [600, 6]
    np.save(tmp_path / "scan.npy", cloud)
    out, aligned = tmp_path / "pose.json", tmp_path / "aligned.npy"
    result = register(tmp_path / "scan.npy", tmp_path / "target.npy", "--out", out, "--write-aligned", aligned,
                      model_dir=model_dir)  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "note" not in result.stderr
    rotation, translation = pose(out)
    written = np.load(aligned)
    assert written.dtype == np.float32 and written.shape == cloud.shape
    assert written[:, 3:].tobytes() == cloud[:, 3:].tobytes()
    assert_moved(written[:, :3], moved(cloud[:, :3], rotation, translation))

    labels = np.arange(len(source), dtype=np.int16)
    np.savez_compressed(tmp_path / "scan.npz", points=source, colors=COLOURS[: len(source)], labels=labels)
    aligned = tmp_path / "aligned.npz"
    result = register(tmp_path / "scan.npz", tmp_path / "target.npy", "--out", out, "--write-aligned", aligned,
                      model_dir=model_dir)  # fmt: skip
    assert result.exit_code == 0, result.output
    rotation, translation = pose(out)
    assert members(aligned) == members(tmp_path / "scan.npz")
    assert member_bytes(aligned, "labels.npy") == member_bytes(tmp_path / "scan.npz", "labels.npy")
    assert_moved(np.load(aligned)["points"], moved(source, rotation, translation))


def test_another_output_format_says_which_columns_and_arrays_it_left(tmp_path, model_dir) -> None:
    source, target = synthetic_pair()
    np.save(tmp_path / "target.npy", target)
    np.save(tmp_path / "scan.npy", np.concatenate([source, NORMALS[: len(source)]], axis=1))
    np.savez(tmp_path / "scan.npz", points=source, colors=COLOURS[: len(source)])
    for name, left in (("scan.npy", "(column 4, column 5, column 6)"), ("scan.npz", "(colors)")):
        result = register(tmp_path / name, tmp_path / "target.npy", "--write-aligned", tmp_path / "aligned.ply",
                          model_dir=model_dir)  # fmt: skip
        assert result.exit_code == 0, result.output
        assert f"{name}'s other fields {left} are kept in a .np" in result.stderr.replace("\n", " ")
        assert read_points(tmp_path / "aligned.ply").shape == (len(source), 3)


def test_sequence_writes_npy_and_npz_frames_as_themselves(tmp_path, model_dir) -> None:
    source, target = synthetic_pair()
    frames = [tmp_path / "f0.npy", tmp_path / "f1.npz", tmp_path / "f2.npy"]
    np.save(frames[0], np.concatenate([target, LABELS[: len(target), None]], axis=1))  # float64 [600, 4]
    np.savez(frames[1], positions=source, normals=NORMALS[: len(source)].astype(np.float32))
    np.save(frames[2], np.asfortranarray(np.concatenate([source, NORMALS[: len(source)]], axis=1)))
    folder, steps = tmp_path / "aligned", tmp_path / "steps.jsonl"
    folder.mkdir()
    result = sequence(frames, folder, model_dir, steps)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in folder.iterdir()) == ["f0.npy", "f1.npz", "f2.npy"]
    assert (folder / "f0.npy").read_bytes() == frames[0].read_bytes()  # frame 0: the identity
    accumulated = [np.asarray(json.loads(line)["accumulated_transform"]) for line in steps.read_text().splitlines()]
    f1, f2 = np.load(folder / "f1.npz"), np.load(folder / "f2.npy")
    rotation, translation = accumulated[0][:3, :3], accumulated[0][:3, 3]
    assert_moved(f1["positions"], moved(source, rotation, translation))
    assert_moved(f1["normals"], moved(NORMALS[: len(source)].astype(np.float32), rotation, 0))
    rotation, translation = accumulated[1][:3, :3], accumulated[1][:3, 3]
    assert f2.flags.f_contiguous and f2[:, 3:].tobytes() == np.load(frames[2])[:, 3:].tobytes()
    assert_moved(f2[:, :3], moved(source, rotation, translation))


# ------------------------------------------------------------------------------------------------- HTTP


def post(client, path: Path, name: str | None = None):
    return post_aligned(client, path, R, T, name)


def test_the_page_downloads_an_npy_and_an_npz_as_themselves_moved(client, tmp_path) -> None:
    np.save(tmp_path / "scan.npy", table("<f4"))
    np.savez_compressed(tmp_path / "scan.npz", positions=XYZ, normals=NORMALS, colors=COLOURS)
    cases = [("scan.npy", None, "scan_aligned.npy"), ("scan.npz", None, "scan_aligned.npz"),
             ("scan.npy", "scan.bin", "scan_aligned.npy"), ("scan.npz", "scan", "scan_aligned.npz")]  # fmt: skip
    for name, upload_name, download in cases:
        answer = post(client, tmp_path / name, upload_name)
        assert answer.status_code == 200, answer.text
        assert answer.headers["content-type"] == "application/octet-stream"
        assert answer.headers["content-disposition"] == f'attachment; filename="{download}"'
        assert int(answer.headers["content-length"]) == len(answer.content)
        write(tmp_path / name, tmp_path / f"cli_{name}")
        assert answer.content == (tmp_path / f"cli_{name}").read_bytes()  # the CLI's file, byte for byte
    written = np.load(io.BytesIO(post(client, tmp_path / "scan.npz").content))
    assert_moved(written["normals"], moved(NORMALS, R, 0))
    assert written["colors"].tobytes() == COLOURS.tobytes()


def test_the_page_downloads_a_structured_array_without_normals(client, tmp_path) -> None:
    """It was a 500 (a ValueError in the writer)."""
    array = np.zeros(N, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("label", "<i4")])
    for k in range(3):
        array["xyz"[k]] = XYZ[:, k]
    array["label"] = LABELS
    np.save(tmp_path / "labelled.npy", array)
    answer = post(client, tmp_path / "labelled.npy")
    assert answer.status_code == 200, answer.text
    written = np.load(io.BytesIO(answer.content))
    assert written.dtype == array.dtype and written["label"].tobytes() == LABELS.tobytes()
    assert_moved(np.stack([written[a] for a in "xyz"], 1), moved(XYZ))


def test_the_page_refuses_an_array_it_cannot_write_moved_with_a_422(client, tmp_path) -> None:
    np.savez_compressed(tmp_path / "bomb.npz", points=XYZ[:20], padding=np.zeros(1 << 19))
    assert_error(post(client, tmp_path / "bomb.npz"), 422, "bomb.npz", "other arrays expand to")
    array = np.concatenate([np.round(XYZ), np.full((N, 1), 2**60)], axis=1).astype(np.int64)
    np.save(tmp_path / "ids.npy", array)
    assert_error(post(client, tmp_path / "ids.npy"), 422, "ids.npy", "2**53")


# ------------------------------------------------------------------------------------ refused before registering


def patched_member(path: Path, name: str, *, flags: int = 0, method: int | None = None) -> None:
    """The archive at ``path`` with member ``name``'s general-purpose flags or'ed with ``flags`` (1: encrypted) and
    its compression method set to ``method``, in its local header and its central directory entry alike (zipfile
    writes neither)."""
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        local, entry = archive.getinfo(name).header_offset, archive.start_dir  # the central directory's start
    while data[entry + 46 : entry + 46 + int.from_bytes(data[entry + 28 : entry + 30], "little")] != name.encode():
        entry = data.find(b"PK\x01\x02", entry + 4)  # the next entry: each holds its name from byte 46
    for at in (local + 6, entry + 8):  # the flags, then the method
        data[at : at + 2] = (int.from_bytes(data[at : at + 2], "little") | flags).to_bytes(2, "little")
        if method is not None:
            data[at + 2 : at + 4] = method.to_bytes(2, "little")
    path.write_bytes(bytes(data))


def unwritable(folder: Path, case: str, xyz: np.ndarray) -> tuple[Path, str]:
    """A cloud of ``xyz [n, 3]`` the reader reads but the writer refuses, and the words of the refusal."""
    wide = np.zeros((len(xyz), 40), dtype=np.int16)  # 80 bytes a row, 320 as float64
    wide[:, :3] = np.round(xyz * 1000)  # millimetres
    labels = np.arange(len(xyz), dtype=np.int32)
    if case == "wide-npy":
        np.save(folder / "wide.npy", wide)
        return folder / "wide.npy", "rows of 40 int16 values would be 320 bytes as float64: at most 256"
    if case == "wide-npz":
        np.savez(folder / "wide.npz", points=wide, labels=labels)
        return folder / "wide.npz", "rows of 40 int16 values would be 320 bytes as float64: at most 256"
    if case == "large-others":
        np.savez_compressed(folder / "bomb.npz", points=xyz, padding=np.zeros(1 << 19))  # 4 MiB of zeros
        return folder / "bomb.npz", "other arrays expand to 4194432 bytes"
    ids = np.concatenate([np.round(xyz * 1000), labels[:, None]], axis=1).astype(np.int64)  # millimetres, an id
    ids[len(xyz) // 2, 3] = 2**53 + 1  # float64 would round it to 2**53
    if case == "ids-npy":
        np.save(folder / "ids.npy", ids)
        return folder / "ids.npy", "an array of int64 holds integers beyond 2**53"
    if case == "ids-npz":  # Fortran order, deflated: the x, y, z columns passed over, the id column read
        np.savez_compressed(folder / "ids.npz", points=np.asfortranarray(ids.astype(">i8")), labels=labels)
        return folder / "ids.npz", "an array of >i8 holds integers beyond 2**53"
    path = folder / f"{case}.npz"
    np.savez(path, points=xyz, labels=labels)
    if case == "encrypted":
        patched_member(path, "labels.npy", flags=0x1)
        return path, "member 'labels.npy' is encrypted"
    patched_member(path, "labels.npy", method=98)  # PPMd: no zipfile decompressor
    return path, "compression method is not supported"


CASES = ["wide-npy", "wide-npz", "large-others", "encrypted", "compression", "ids-npy", "ids-npz"]


@pytest.mark.parametrize("case", CASES)
def test_what_the_header_decides_is_refused_before_writing_as_the_writer_refuses_it(tmp_path, case) -> None:
    """``check_moved_npy`` / ``check_moved_npz`` (the CLI's check before registering) refuse what the writer refuses
    with the writer's own words, reading the header alone; the file is read as a cloud all the same."""
    source, words = unwritable(tmp_path, case, XYZ)
    assert read_points(source).shape == (N, 3)
    kind = source.suffix[1:]
    with open(source, "rb") as f:
        with pytest.raises(PointCloudFormatError, match=re.escape(words)):
            check_moved(f, kind)
        assert f.tell() == 0
    with pytest.raises(PointCloudFormatError, match=re.escape(words)):
        write(source, tmp_path / f"aligned.{kind}")
    assert not (tmp_path / f"aligned.{kind}").exists()


def test_the_check_passes_what_is_written(tmp_path) -> None:
    ids = np.concatenate([np.round(XYZ), np.full((N, 1), -(2**53))], axis=1).astype(np.int64)  # exact in float64
    np.save(tmp_path / "ids.npy", ids)
    np.save(tmp_path / "fortran.npy", np.asfortranarray(ids))
    np.savez_compressed(tmp_path / "ids.npz", points=np.abs(ids).astype(np.uint64))
    np.savez_compressed(tmp_path / "o3d.npz", positions=XYZ, normals=NORMALS, colors=COLOURS)
    np.save(tmp_path / "narrow.npy", np.zeros((N, 32), dtype=np.int8))  # 256 bytes a row as float64: the limit
    for name in ("ids.npy", "fortran.npy", "ids.npz", "o3d.npz", "narrow.npy"):
        check_moved(tmp_path / name, name[-3:])
        write(tmp_path / name, tmp_path / f"aligned-{name}")
    for name in ("ids.npy", "fortran.npy"):
        assert (np.load(tmp_path / f"aligned-{name}")[:, 3] == -(2**53)).all()


def test_the_integer_check_of_a_2_000_000_point_array_reads_it_a_block_at_a_time(tmp_path) -> None:
    """8-byte integers are the one array whose data the check reads (it was the writer's to find, after registering):
    in blocks, never the 64 MB array whole; the value beyond 2**53 in its last row is found. (``check_moved`` then
    asks the reader, which reads the points once, whether the file is the reader's to refuse.)"""
    rows = 2_000_000
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<i8", "fortran_order": False, "shape": (rows, 4)})
    with open(tmp_path / "big.npy", "wb") as f:  # a sparse file: the header, 64 MB of zeros, then a last row
        f.write(header.getvalue())
        f.seek(len(header.getvalue()) + (rows - 1) * 32)
        f.write(np.array([[0, 0, 0, 2**53 + 1]], dtype="<i8").tobytes())
    tracemalloc.start()
    try:
        with open(tmp_path / "big.npy", "rb") as f, pytest.raises(PointCloudFormatError, match=r"beyond 2\*\*53"):
            check_moved_npy(f)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, peak  # 4 MiB blocks (the array: 64 MB)


def test_a_float16_array_too_wide_in_map_coordinates_is_refused_before_registering_too(tmp_path) -> None:
    """float16 rows of 40 columns are 160 bytes as float32, 320 as float64: the check before registering (x, y, z not
    widened) passed them, and the writer refused them once the pose had moved the points into map coordinates (exit 1
    after registering). The rows are now measured as float64 by both, since only the pose tells which is written."""
    halves = np.zeros((N, 40), dtype=np.float16)  # [N, 40]
    halves[:, :3] = XYZ
    np.save(tmp_path / "halves.npy", halves)
    np.save(tmp_path / "narrow.npy", halves[:, :32])  # 256 bytes a row as float64: the limit
    assert read_points(tmp_path / "halves.npy").shape == (N, 3)
    words = re.escape("rows of 40 float16 values would be 320 bytes as float64: at most 256")
    with pytest.raises(PointCloudFormatError, match=words):
        check_moved(tmp_path / "halves.npy", "npy")
    for translation in (T, UTM):
        with pytest.raises(PointCloudFormatError, match=words):
            write(tmp_path / "halves.npy", tmp_path / "aligned.npy", translation=translation)
    check_moved(tmp_path / "narrow.npy", "npy")
    write(tmp_path / "narrow.npy", tmp_path / "aligned.npy", translation=UTM)
    assert np.load(tmp_path / "aligned.npy").dtype == np.float64


class CountingFile(io.FileIO):
    """A file that counts the bytes read from it."""

    read_bytes = 0

    def read(self, size=-1):
        data = super().read(size)
        self.read_bytes += len(data)
        return data

    def readinto(self, buffer):
        got = super().readinto(buffer)
        self.read_bytes += got or 0
        return got


def test_the_check_of_a_2_000_000_point_array_reads_its_headers_only(tmp_path) -> None:
    rows = 2_000_000
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<i2", "fortran_order": False, "shape": (rows, 40)})
    with open(tmp_path / "big.npy", "wb") as f:  # a sparse file: the header, then 160 MB of zeros
        f.write(header.getvalue())
        f.truncate(len(header.getvalue()) + rows * 80)
    with zipfile.ZipFile(tmp_path / "big.npz", "w") as archive:  # stored: the cloud's 24 MB, then an encrypted member
        with archive.open("points.npy", "w") as member:
            np.lib.format.write_array(member, np.zeros((rows, 3), dtype=np.float32))
        archive.writestr("labels.npy", b"")
    patched_member(tmp_path / "big.npz", "labels.npy", flags=0x1)
    for name, words in (("big.npy", "would be 320 bytes"), ("big.npz", "is encrypted")):
        with CountingFile(tmp_path / name) as f:
            with pytest.raises(PointCloudFormatError, match=words):
                (check_moved_npy if name.endswith("npy") else check_moved_npz)(f)
            assert f.read_bytes < 100_000, (name, f.read_bytes)


@pytest.mark.parametrize("case", CASES)
def test_register_refuses_an_array_it_cannot_write_before_registering(tmp_path, model_dir, case) -> None:
    """Each was exit 1 "cannot write" once registered (seconds; minutes in a sequence): now exit 2 before it, and the
    registration's record (``--out``, written before the aligned cloud) never exists."""
    source_xyz, target = synthetic_pair()
    source, words = unwritable(tmp_path, case, source_xyz.astype(np.float64))
    np.save(tmp_path / "target.npy", target * (1000 if case.startswith(("wide", "ids")) else 1))
    out, aligned = tmp_path / "pose.json", tmp_path / f"aligned{source.suffix}"
    result = register(source, tmp_path / "target.npy", "--out", out, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    stderr = " ".join(result.stderr.split())
    assert (
        f"--write-aligned {aligned.name}: {source.name} cannot be written moved as {source.suffix[1:].upper()}: "
        in stderr
    )
    assert words in stderr
    assert not out.exists() and not aligned.exists()


def frames_then(tmp_path: Path, last: Callable[[np.ndarray], Path]) -> tuple[list[Path], Path]:
    """Three frames for ``mfgnet sequence``: the synthetic target, its source, and ``last`` made from the source
    (float64); and an empty folder for the aligned frames."""
    source, target = synthetic_pair()
    frames = [tmp_path / "f0.npy", tmp_path / "f1.npy"]
    np.save(frames[0], target)
    np.save(frames[1], source)
    folder = tmp_path / "aligned"
    folder.mkdir()
    return [*frames, last(source.astype(np.float64))], folder


def test_sequence_refuses_a_frame_it_cannot_write_before_the_first_registration(tmp_path, model_dir) -> None:
    """The last frame of three: it was found once both steps had been registered and frames 0 and 1 written."""
    frames, folder = frames_then(tmp_path, lambda source: unwritable(tmp_path, "encrypted", source)[0])
    result = sequence(frames, folder, model_dir)
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    stderr = " ".join(result.stderr.split())
    assert f"--write-aligned {folder / 'encrypted.npz'}: encrypted.npz cannot be written moved as NPZ" in stderr
    assert "member 'labels.npy' is encrypted" in stderr
    assert result.stdout == "" and list(folder.iterdir()) == []  # no step's JSON line, no frame written


@pytest.mark.parametrize("case", CASES)
def test_the_page_still_refuses_what_the_cli_now_refuses_before_registering_with_a_422(client, tmp_path, case):
    source, words = unwritable(tmp_path, case, XYZ)
    assert_error(post(client, source), 422, source.name, "cannot be written moved", words)


# ------------------------------------------------------------------------------ a source the reader refuses


def unreadable(folder: Path, case: str, xyz: np.ndarray) -> tuple[Path, str]:
    """A cloud of ``xyz [n, 3]`` damaged so that the reader refuses it, and the words of the reader's refusal."""
    np.save(folder / "whole.npy", xyz)
    whole = (folder / "whole.npy").read_bytes()
    if case == "cut-npy":
        (folder / "cut.npy").write_bytes(whole[: len(whole) // 2])
        return folder / "cut.npy", f"truncated .npy file: shape [{len(xyz)}, 3] of float64 needs"
    if case == "header-npy":
        (folder / "header.npy").write_bytes(b"\x93NUMPY\x01\x00" + b"{not a dict}")
        return folder / "header.npy", "not a valid .npy file (unreadable header)"
    if case == "cut-npz":
        np.savez(folder / "whole.npz", points=xyz, labels=np.arange(len(xyz)))
        (folder / "cut.npz").write_bytes((folder / "whole.npz").read_bytes()[:-100])  # its directory cut off
        return folder / "cut.npz", "not a valid .npz archive"
    with zipfile.ZipFile(folder / "member.npz", "w") as archive:  # the cloud member cut short
        archive.writestr("points.npy", whole[: len(whole) // 2])
    return folder / "member.npz", f"truncated .npy file: shape [{len(xyz)}, 3] of float64 needs"


UNREADABLE = ["cut-npy", "header-npy", "cut-npz", "cut-member-npz"]


@pytest.mark.parametrize("case", UNREADABLE)
def test_a_source_the_reader_refuses_is_no_writers_refusal(tmp_path, case) -> None:
    """The check before registering parses what the reader parses; where the reader refuses the file, that is not the
    writer's to say (it said 'cannot be written moved as NPY: truncated .npy file ...'): reading it says why."""
    source, words = unreadable(tmp_path, case, XYZ)
    with pytest.raises(PointCloudFormatError, match=re.escape(words)):
        read_points(source)
    check_moved(source, source.suffix[1:])


@pytest.mark.parametrize("case", UNREADABLE)
def test_register_names_the_read_failure_of_a_source_to_write_aligned(tmp_path, model_dir, case) -> None:
    """Exit 2 naming the read failure, as for a PLY, PCD or LAS source the reader refuses, in process and with
    --server (the source is read here before anything is sent: nothing listens at the address)."""
    source_xyz, target = synthetic_pair()
    source, words = unreadable(tmp_path, case, source_xyz.astype(np.float64))
    np.save(tmp_path / "target.npy", target)
    aligned = tmp_path / f"aligned{source.suffix}"
    args = [str(source), str(tmp_path / "target.npy"), "--write-aligned", str(aligned)]
    for result in (
        register(*args, model_dir=model_dir),
        runner.invoke(app, ["register", *args, "--server", f"http://127.0.0.1:{free_port()}"]),
    ):
        assert result.exit_code == 2 and "Traceback" not in result.output, result.output
        stderr = " ".join(result.stderr.split())
        assert f"error: {source.name}: {words}" in stderr and "cannot be written moved" not in stderr, stderr
        assert not aligned.exists()


def test_sequence_names_the_read_failure_of_a_frame_to_write_aligned(tmp_path, model_dir) -> None:
    """A frame the reader refuses fails as any unreadable frame does (its steps before it written), named as read."""
    frames, folder = frames_then(tmp_path, lambda source: unreadable(tmp_path, "cut-npy", source)[0])
    result = sequence(frames, folder, model_dir)
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    stderr = " ".join(result.stderr.split())
    assert f"frame 2 {frames[2]}: cut.npy: truncated .npy file" in stderr and "cannot be written" not in stderr, stderr


@pytest.mark.parametrize("case", UNREADABLE)
def test_the_page_names_the_read_failure_of_an_unreadable_source_with_a_400(client, tmp_path, case) -> None:
    source, words = unreadable(tmp_path, case, XYZ)
    body = assert_error(post(client, source), 400, source.name, words)
    assert "cannot be written moved" not in body["error"]
