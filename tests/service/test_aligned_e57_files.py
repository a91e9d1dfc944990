"""An aligned E57 file is E57, with everything it held (``service.formats.moved_e57``): every scan's and image's pose
composed with the registration, its points, intensities, colours and images copied as they are. Checked with our
reader, the Rust ``e57`` library (which checks every page's CRC-32C) and pye57 (libE57Format); through
``mfgnet register`` / ``sequence --write-aligned`` and the real server's ``POST /v1/register/aligned``."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import e57
import numpy as np
import pye57
import pytest
from aligned_runs import register, sequence
from api_server import assert_error
from cli_support import synthetic_pair
from e57_xml import _paged, with_xml, xml_of
from pye57 import libe57
from scipy.spatial.transform import Rotation

from service.formats import PointCloudFormatError, read_cloud
from service.formats.e57 import MAX_XML_BYTES, read_e57
from service.formats.moved import write_moved
from service.formats.moved_e57 import _moved_xml, check_moved_e57

HEADER = struct.Struct("<8sIIQQQQ")  # signature, version, file length, XML offset, XML length, page size
R = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True).as_matrix()
T = np.array([512_345.25, 4_123_456.5, 150.125])  # into map coordinates: float64 poses keep them
SCAN_POSES = [  # w, x, y, z; translation
    (np.array([0.5, 0.5, 0.5, 0.5]), np.array([1.0, 2.0, 3.0])),
    (np.array([np.cos(0.3), 0.0, np.sin(0.3), 0.0]), np.array([-4.0, 5.0, 6.0])),
    None,  # a scan without a pose: the identity
]
IMAGE_POSE = (np.array([np.cos(0.2), 0.0, 0.0, -np.sin(0.2)]), np.array([7.0, 8.0, 9.0]))
IMAGE_BYTES = [bytes(range(256)) * 8, bytes(range(255, -1, -1)) * 5]  # two images' blobs, 2,048 and 1,280 bytes


def rotation(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def _image(imf, number: int, pose: tuple | None) -> libe57.StructureNode:
    image = libe57.StructureNode(imf)
    image.set("guid", libe57.StringNode(imf, f"{{image-{number}}}"))
    pinhole = libe57.StructureNode(imf)
    pinhole.set("jpegImage", libe57.BlobNode(imf, len(IMAGE_BYTES[number])))
    for name in ("imageWidth", "imageHeight"):
        pinhole.set(name, libe57.IntegerNode(imf, 16, 0, 1000))
    for name, value in (("pixelWidth", 1e-5), ("pixelHeight", 1e-5), ("focalLength", 0.01)):
        pinhole.set(name, libe57.FloatNode(imf, value))
    for name in ("principalPointX", "principalPointY"):
        pinhole.set(name, libe57.FloatNode(imf, 8.0))
    image.set("pinholeRepresentation", pinhole)
    if pose is not None:
        node = libe57.StructureNode(imf)
        for name, axes, values in (("rotation", "wxyz", pose[0]), ("translation", "xyz", pose[1])):
            part = libe57.StructureNode(imf)
            for axis, value in zip(axes, values, strict=True):
                part.set(axis, libe57.FloatNode(imf, float(value)))
            node.set(name, part)
        image.set("pose", node)
    return image


def write_project(path: Path, clouds: list[np.ndarray], poses: list, images: bool = True) -> None:
    """A scanner's project: scans of ``clouds [n, 3]`` (in their own frames) with intensity and colours, each with
    its pose from ``poses`` (written by pye57) or none (``None``: written through libE57Format's nodes), and two
    images (one with a pose, one without) with their blobs."""
    writer = pye57.E57(str(path), mode="w")
    imf = writer.image_file
    rng = np.random.default_rng(3)
    for number, (xyz, pose) in enumerate(zip(clouds, poses, strict=True)):
        if pose is not None:
            data = {f"cartesian{axis}": np.ascontiguousarray(xyz[:, k]) for k, axis in enumerate("XYZ")}
            data["intensity"] = rng.random(len(xyz))
            for name in ("colorRed", "colorGreen", "colorBlue"):
                data[name] = rng.integers(0, 256, len(xyz)).astype(np.uint8)
            writer.write_scan_raw(data, rotation=pose[0], translation=pose[1])
            continue
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, f"{{unposed-{number}}}"))
        prototype = libe57.StructureNode(imf)
        for name in ("cartesianX", "cartesianY", "cartesianZ", "intensity"):
            prototype.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
        points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
        scan.set("points", points)
        writer.data3d.append(scan)
        columns = [np.ascontiguousarray(xyz[:, k], dtype=np.float64) for k in range(3)] + [rng.random(len(xyz))]
        buffers = libe57.VectorSourceDestBuffer()
        for name, column in zip(("cartesianX", "cartesianY", "cartesianZ", "intensity"), columns, strict=True):
            buffers.append(libe57.SourceDestBuffer(imf, name, column, len(column), True, False))
        scan_writer = points.writer(buffers)
        scan_writer.write(len(xyz))
        scan_writer.close()
    if images:
        for number, pose in enumerate((IMAGE_POSE, None)):
            image = _image(imf, number, pose)
            writer.root["images2D"].append(image)
            blob = np.frombuffer(IMAGE_BYTES[number], dtype=np.uint8).copy()
            image["pinholeRepresentation"]["jpegImage"].write(blob, 0, len(blob))
    writer.close()


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("e57") / "project.e57"
    rng = np.random.default_rng(0)
    write_project(path, [rng.normal(size=(200 + k, 3)) * 5 for k in range(3)], SCAN_POSES)
    return path


def moved_to(source: Path, out: Path, rotation_: np.ndarray = R, translation: np.ndarray = T) -> Path:
    write_moved(source, out, rotation_, translation, largest=float(np.abs(translation).max()) + 100)
    return out


def image_poses(path: Path) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Each image's pose as pye57 (libE57Format) reads it."""
    found = []
    reader = pye57.E57(str(path))  # held: its nodes need it
    images = reader.root["images2D"]
    for k in range(images.childCount()):
        image = images[k]
        if not image.isDefined("pose"):
            found.append(None)
            continue
        pose = image["pose"]
        found.append(
            (
                np.array([pose["rotation"][a].value() for a in "wxyz"]),
                np.array([pose["translation"][a].value() for a in "xyz"]),
            )
        )
    return found


def blobs(path: Path) -> list[bytes]:
    reader = pye57.E57(str(path))  # held: its nodes need it
    images = reader.root["images2D"]
    found = []
    for k in range(images.childCount()):
        blob = images[k]["pinholeRepresentation"]["jpegImage"]
        data = np.zeros(blob.byteCount(), dtype=np.uint8)
        blob.read(data, 0, len(data))
        found.append(data.tobytes())
    return found


def without_poses(xml: bytes) -> bytes:
    return re.sub(rb"\s*<pose type=\"Structure\">.*?</pose>", b"", xml, flags=re.DOTALL)


# ------------------------------------------------------------------------------------------------- the file


def test_an_e57_project_comes_back_as_e57_with_its_poses_composed_and_its_data_copied(project, tmp_path) -> None:
    out = moved_to(project, tmp_path / "aligned.e57")
    with open(project, "rb") as f, open(out, "rb") as g:
        before, after = read_e57(f, None), read_e57(g, None)
    np.testing.assert_allclose(after, before @ R.T + T, rtol=0, atol=1e-8)  # our reader: the moved points
    rust_before, rust_after = e57.read_points(str(project)), e57.read_points(str(out))  # the library checks CRCs
    np.testing.assert_allclose(rust_after.points, rust_before.points @ R.T + T, rtol=0, atol=1e-8)
    assert np.array_equal(rust_after.intensity, rust_before.intensity)
    assert np.array_equal(rust_after.color, rust_before.color)
    lib_before, lib_after = pye57.E57(str(project)), pye57.E57(str(out))  # libE57Format, scan by scan
    assert lib_after.scan_count == 3
    for k in range(3):
        scans = [
            e.read_scan(k, intensity=True, colors=k < 2, transform=True, ignore_missing_fields=True)
            for e in (lib_before, lib_after)
        ]
        xyz = [np.stack([s[f"cartesian{a}"] for a in "XYZ"], axis=1) for s in scans]
        np.testing.assert_allclose(xyz[1], xyz[0] @ R.T + T, rtol=0, atol=1e-8)
        for name in scans[0]:
            if not name.startswith("cartesian"):
                assert np.array_equal(scans[1][name], scans[0][name]), (k, name)
    moved_images = image_poses(out)  # the posed image turned with the scans; the other one gains the pose
    q, offset = moved_images[0]
    np.testing.assert_allclose(rotation(q), R @ rotation(IMAGE_POSE[0]), atol=1e-12)
    np.testing.assert_allclose(offset, R @ IMAGE_POSE[1] + T, rtol=0, atol=1e-8)
    np.testing.assert_allclose(rotation(moved_images[1][0]), R, atol=1e-12)
    np.testing.assert_allclose(moved_images[1][1], T, rtol=0, atol=0)
    assert blobs(out) == IMAGE_BYTES == blobs(project)
    for w, *_ in [*(p[0] for p in moved_images), *(lib_after.get_header(k).rotation for k in range(3))]:
        assert w >= 0  # the sign written: w >= 0, and each quaternion of unit norm
    old, new = xml_of(project.read_bytes()), xml_of(out.read_bytes())
    assert without_poses(new) == without_poses(old)  # every other byte of the XML kept
    assert b"<translation" in new and new.count(b"<pose ") == 5  # three scans' poses, two images'


def test_the_binary_sections_are_copied_and_the_xml_overwritten_in_place_where_it_is_last(project, tmp_path) -> None:
    data, out = project.read_bytes(), moved_to(project, tmp_path / "aligned.e57").read_bytes()
    _, _, _, _, offset, xml_length, _ = HEADER.unpack_from(data)
    _, _, _, new_length, new_offset, new_xml_length, page = HEADER.unpack_from(out)
    assert new_offset == offset and new_length == len(out) and len(out) % page == 0
    assert new_xml_length == len(xml_of(out)) != xml_length
    start = offset - offset % page  # the pages before the XML's: byte for byte, page 0's header and CRC aside
    assert out[HEADER.size : 1020] == data[HEADER.size : 1020] and out[1024:start] == data[1024:start]


def test_an_xml_section_that_is_not_last_is_appended_and_the_file_kept_before_it(project, tmp_path) -> None:
    data = project.read_bytes()
    padded = tmp_path / "padded.e57"
    padded.write_bytes(data + _paged(b"\0" * 1020))  # a page after the XML section
    out = moved_to(padded, tmp_path / "aligned.e57").read_bytes()
    _, _, _, new_length, new_offset, _, _ = HEADER.unpack_from(out)
    assert new_offset == len(data) + 1024 and new_length == len(out)
    assert (
        out[HEADER.size : 1020] == data[HEADER.size : 1020]
        and out[1024 : len(data) + 1024] == padded.read_bytes()[1024:]
    )
    rust_before, rust_after = e57.read_points(str(project)), e57.read_points(str(tmp_path / "aligned.e57"))
    np.testing.assert_allclose(rust_after.points, rust_before.points @ R.T + T, rtol=0, atol=1e-8)
    assert blobs(tmp_path / "aligned.e57") == IMAGE_BYTES


@pytest.mark.parametrize(
    ("old", "new"),
    [
        # a pose without a translation, a rotation whose x is an empty element (0)
        (rb"(<pose type=\"Structure\">\s*<rotation type=\"Structure\">.*?</rotation>)\s*<translation .*?</translation>",
         rb"\1"),
        (rb"<x type=\"Float\">5e-01</x>", b'<x type="Float">0.5</x>'),
        # a pose as an empty element
        (rb"<pose type=\"Structure\">\s*<rotation type=\"Structure\">\s*<w type=\"Float\">9.*?</pose>",
         b'<pose type="Structure"/>'),
    ],
    ids=["no-translation", "plain", "empty-pose"],
)  # fmt: skip
def test_poses_written_otherwise_are_spliced_and_read_moved(project, tmp_path, old, new) -> None:
    data = project.read_bytes()
    xml, count = re.subn(old, new, xml_of(data), count=1, flags=re.DOTALL)
    assert count == 1
    source = tmp_path / "edited.e57"
    source.write_bytes(with_xml(data, xml))
    out = moved_to(source, tmp_path / "aligned.e57")
    with open(source, "rb") as f, open(out, "rb") as g:
        np.testing.assert_allclose(read_e57(g, None), read_e57(f, None) @ R.T + T, rtol=0, atol=1e-8)
    rust_before, rust_after = e57.read_points(str(source)), e57.read_points(str(out))
    np.testing.assert_allclose(rust_after.points, rust_before.points @ R.T + T, rtol=0, atol=1e-8)


def damaged(project: Path, folder: Path, name: str = "damaged.e57") -> Path:
    """``project`` with its first image's rotation quaternion of norm 2 (which the reader reads: it checks the
    scans' quaternions, and the library does not normalise an image's)."""
    data = project.read_bytes()
    xml = xml_of(data)
    at = xml.index(b"<images2D")
    edited = xml[:at] + re.sub(rb'<w type="Float">[^<]*</w>', b'<w type="Float">2</w>', xml[at:], count=1)
    assert edited != xml
    path = folder / name
    path.write_bytes(with_xml(data, edited))
    return path


def test_an_e57_whose_xml_cannot_be_rewritten_is_refused_naming_why(project, tmp_path) -> None:
    source = damaged(project, tmp_path)
    with pytest.raises(PointCloudFormatError, match=r"E57 image 0's pose has a rotation quaternion of norm 2\.0098"):
        moved_to(source, tmp_path / "aligned.e57")
    assert not (tmp_path / "aligned.e57").exists() and [p.name for p in tmp_path.iterdir()] == ["damaged.e57"]


EXTENSION_POSE = (
    b'<ext:pose type="Structure" xmlns:ext="urn:example"><rotation type="Structure"><w type="Float">1</w>'
    b'<x type="Float">0</x><y type="Float">0</y><z type="Float">0</z></rotation><translation type="Structure">'
    b'<x type="Float">100</x><y type="Float">0</y><z type="Float">0</z></translation></ext:pose>'
)


@pytest.mark.parametrize("where", ["before", "instead"])
def test_a_scan_with_a_pose_element_of_another_namespace_is_refused(project, tmp_path, where) -> None:
    """The e57 library (our reader) takes a scan's first child of the local name ``pose`` whatever its namespace: an
    extension's pose before E57's (or instead of one) was read as the pose, and the file written with E57's composed
    (or a new one added after it) read back unmoved."""
    data = project.read_bytes()
    xml = xml_of(data)
    pose = re.search(rb'<pose type="Structure">.*?</pose>', xml, flags=re.DOTALL).group(0)
    source = tmp_path / "extended.e57"
    source.write_bytes(with_xml(data, xml.replace(pose, EXTENSION_POSE + (pose if where == "before" else b""), 1)))
    with open(source, "rb") as f:
        read_e57(f, None)  # the reader reads it: the extension's pose
    message = r"E57 scan 0's pose cannot be rewritten: .* 'pose' element of another namespace \('urn:example'\)"
    with pytest.raises(PointCloudFormatError, match=message):
        moved_to(source, tmp_path / "aligned.e57")
    with open(source, "rb") as f, pytest.raises(PointCloudFormatError, match=message):
        check_moved_e57(f)  # before registering: the CLI's usage error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["extended.e57"]


def test_an_e57_whose_poses_added_would_take_its_xml_beyond_the_readers_limits_is_refused(project, tmp_path) -> None:
    """9,000 images without a pose (2 elements each, 18,000 in all) gain 10 elements each: the file written was one
    that our reader refuses (more than 100,000 elements), though the libraries read it."""
    data = project.read_bytes()
    images = b"".join(
        b'<vectorChild type="Structure"><guid type="String">%d</guid></vectorChild>' % k for k in range(9000)
    )
    xml = re.sub(rb"(<images2D[^>]*>)", lambda m: m.group(1) + images, xml_of(data), count=1)
    source = tmp_path / "catalogue.e57"
    source.write_bytes(with_xml(data, xml))
    with open(source, "rb") as f:
        read_e57(f, None)  # read as it is
    message = "with its poses composed would not be read back: has more than 100000 elements"
    with pytest.raises(PointCloudFormatError, match=message):
        moved_to(source, tmp_path / "aligned.e57")
    with open(source, "rb") as f, pytest.raises(PointCloudFormatError, match=message):
        check_moved_e57(f)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["catalogue.e57"]


def test_an_e57_that_poses_of_longer_numbers_would_take_beyond_the_byte_limit_is_refused_before_registering(
    project, tmp_path
) -> None:
    """The check before registering composed the identity, whose numbers print short (``1.0``, ``0.0``): an XML
    section that a registration's pose (numbers of up to 24 characters) takes beyond ``MAX_XML_BYTES`` passed it, and
    was refused once registered (exit 1). It now counts each number written at its longest."""
    xml = xml_of(project.read_bytes())
    shortest, longest = (len(_moved_xml(xml, np.eye(3), np.zeros(3))[0]), len(_moved_xml(xml, R, T)[0]))
    assert longest > shortest + 100
    padding = MAX_XML_BYTES - (shortest + longest) // 2 - len(b"<!---->")  # between the two once padded
    padded = xml.replace(b"<data3D", b"<!--" + b"p" * padding + b"--><data3D", 1)
    source = tmp_path / "near-the-limit.e57"
    source.write_bytes(with_xml(project.read_bytes(), padded))
    with open(source, "rb") as f:
        read_e57(f, None)  # read as it is
        with pytest.raises(PointCloudFormatError, match=f"would not be read back: .* at most {MAX_XML_BYTES}"):
            check_moved_e57(f)
    with pytest.raises(PointCloudFormatError, match=f"would not be read back: it would have .* {MAX_XML_BYTES}"):
        moved_to(source, tmp_path / "aligned.e57")


class CountedBytes(bytes):
    """An XML section that counts the bytes sliced out of it."""

    sliced = 0

    def __getitem__(self, key):
        part = super().__getitem__(key)
        if isinstance(key, slice):
            CountedBytes.sliced += len(part)
        return part


def test_the_poses_inserted_take_work_linear_in_the_xml_not_a_copy_of_it_each(project) -> None:
    """Each pose inserted into an element without one copied the whole XML before that element to find the white space
    before its end tag: quadratic (16,000 images in 6 MB took 9 times as long as 4,000 in 1.5 MB, 6.4 s). The bytes
    sliced out of the text are now about its length."""
    images = b"".join(
        b'<vectorChild type="Structure"><guid type="String">%d</guid></vectorChild>' % k for k in range(2000)
    )
    xml = re.sub(rb"(<images2D[^>]*>)", lambda m: m.group(1) + images, xml_of(project.read_bytes()), count=1)
    CountedBytes.sliced = 0
    moved, _ = _moved_xml(CountedBytes(xml), R, T)
    assert moved.count(b"<pose ") == 2005  # three scans' poses, two images' and 2,000 new ones
    assert CountedBytes.sliced < 3 * len(xml), CountedBytes.sliced


# -------------------------------------------------------------------------------------------------- the CLI

SOURCE, TARGET = synthetic_pair()  # [600, 3] float32 each
SCAN_POSE = (np.array([np.cos(0.4), np.sin(0.4), 0.0, 0.0]), np.array([0.5, -0.25, 2.0]))


def scan_of(xyz: np.ndarray, path: Path) -> Path:
    """``xyz`` (the file's frame) as one scan with :data:`SCAN_POSE` and two images."""
    local = (xyz.astype(np.float64) - SCAN_POSE[1]) @ rotation(SCAN_POSE[0])  # R_i @ local + t_i = xyz
    write_project(path, [local], [SCAN_POSE])
    return path


def test_register_writes_an_e57_source_as_e57_moved(tmp_path, model_dir) -> None:
    source, target = scan_of(SOURCE, tmp_path / "scan.e57"), tmp_path / "target.npy"
    np.save(target, TARGET)
    out, aligned = tmp_path / "pose.json", tmp_path / "aligned.e57"
    result = register(source, target, "--out", out, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    record = json.loads(out.read_text())
    rotation_, translation = np.asarray(record["rotation"]), np.asarray(record["translation"])
    before, after = e57.read_points(str(source)), e57.read_points(str(aligned))
    np.testing.assert_allclose(after.points, before.points @ rotation_.T + translation, rtol=0, atol=1e-9)
    assert np.array_equal(after.intensity, before.intensity) and np.array_equal(after.color, before.color)
    assert blobs(aligned) == IMAGE_BYTES and "note" not in result.stderr


def test_an_e57_source_to_another_format_holds_x_y_z_and_says_what_it_left(tmp_path, model_dir) -> None:
    source, target = scan_of(SOURCE, tmp_path / "scan.e57"), tmp_path / "target.npy"
    np.save(target, TARGET)
    aligned = tmp_path / "aligned.ply"
    result = register(source, target, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    assert "aligned.ply holds x, y, z only; scan.e57's other fields (intensity, colorRed, colorGreen, colorBlue, " in (
        " ".join(result.stderr.split())
    )
    assert "images) are kept in a .e57 output" in " ".join(result.stderr.split())


def test_register_refuses_an_e57_whose_xml_cannot_be_rewritten_before_registering(project, tmp_path, model_dir):
    source = damaged(project, tmp_path)
    aligned = tmp_path / "aligned.e57"
    result = register(source, tmp_path / "missing.npy", "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "--write-aligned aligned.e57: damaged.e57 cannot be written moved as E57" in result.stderr
    assert (
        "image 0's pose has a rotation quaternion of norm 2.0098" in result.stderr
        and not (tmp_path / "aligned.e57").exists()
    )


@pytest.mark.parametrize("cut", ["pages", "xml"])
def test_register_names_the_read_failure_of_an_e57_source_the_reader_refuses(project, tmp_path, model_dir, cut) -> None:
    """The check before registering parses what the reader parses: an E57 file cut short was said to be one that
    'cannot be written moved as E57'; the error is the reader's now, as for a PLY, PCD or LAS source."""
    data = project.read_bytes()
    source = tmp_path / "cut.e57"
    source.write_bytes(data[: len(data) // 2] if cut == "xml" else data[:-100])  # its XML section, or whole pages
    with pytest.raises(PointCloudFormatError) as refused:
        read_cloud(source)
    result = register(
        source, tmp_path / "missing.npy", "--write-aligned", tmp_path / "aligned.e57", model_dir=model_dir
    )
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    stderr = " ".join(result.stderr.split())
    assert f"error: {refused.value}" in stderr and "cannot be written moved" not in stderr, stderr
    assert not (tmp_path / "aligned.e57").exists()


def test_an_e57_output_of_another_format_is_a_usage_error(tmp_path, model_dir) -> None:
    source = tmp_path / "scan.npy"
    np.save(source, SOURCE)
    result = register(source, source, "--write-aligned", tmp_path / "a.e57", model_dir=model_dir)
    assert result.exit_code == 2 and "an E57 file is written only from an E57 source" in result.stderr


def test_sequence_writes_e57_frames_as_e57_moved_into_frame_0(tmp_path, model_dir) -> None:
    turn = Rotation.from_euler("z", -8.0, degrees=True).as_matrix()
    frames = [scan_of(SOURCE, tmp_path / "f0.e57"), scan_of(SOURCE.astype(np.float64) @ turn.T, tmp_path / "f1.e57")]
    folder, steps = tmp_path / "aligned", tmp_path / "steps.jsonl"
    folder.mkdir()
    result = sequence(frames, folder, model_dir, steps)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in folder.iterdir()) == ["f0.e57", "f1.e57"]
    accumulated = [np.eye(4), np.asarray(json.loads(steps.read_text().splitlines()[0])["accumulated_transform"])]
    for frame, pose in zip(frames, accumulated, strict=True):
        before, after = e57.read_points(str(frame)), e57.read_points(str(folder / frame.name))
        expected = before.points @ pose[:3, :3].T + pose[:3, 3]
        np.testing.assert_allclose(after.points, expected, rtol=0, atol=1e-9)
        assert np.array_equal(after.color, before.color) and blobs(folder / frame.name) == IMAGE_BYTES


def test_sequence_refuses_an_e57_frame_whose_xml_cannot_be_rewritten_before_registering(project, tmp_path, model_dir):
    frames = [scan_of(SOURCE, tmp_path / "f0.e57"), damaged(project, tmp_path, "f1.e57")]
    folder = tmp_path / "aligned"
    folder.mkdir()
    result = sequence(frames, folder, model_dir)
    assert result.exit_code == 2 and "f1.e57 cannot be written moved as E57" in result.stderr
    assert list(folder.iterdir()) == []


# ----------------------------------------------------------------------------------------------- the server


def post(client, path: Path, matrix: np.ndarray):
    return client.post(
        "/v1/register/aligned",
        files={"source": (path.name, path.read_bytes())},
        data={"transform": json.dumps(matrix.tolist())},
    )


def test_the_pages_download_of_an_e57_upload_is_e57_moved(client, project, tmp_path) -> None:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = R, T
    answer = post(client, project, matrix)
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"] == "model/e57"
    assert answer.headers["content-disposition"] == 'attachment; filename="project_aligned.e57"'
    assert answer.content == moved_to(project, tmp_path / "cli.e57").read_bytes()  # the CLI's file
    (tmp_path / "answer.e57").write_bytes(answer.content)
    before, after = e57.read_points(str(project)), e57.read_points(str(tmp_path / "answer.e57"))
    np.testing.assert_allclose(after.points, before.points @ R.T + T, rtol=0, atol=1e-8)
    assert blobs(tmp_path / "answer.e57") == IMAGE_BYTES


def test_an_e57_upload_whose_xml_cannot_be_rewritten_is_a_422(client, project, tmp_path) -> None:
    answer = post(client, damaged(project, tmp_path), np.eye(4))
    assert_error(answer, 422, "damaged.e57", "cannot be written moved", "image 0", "norm 2.0098")
