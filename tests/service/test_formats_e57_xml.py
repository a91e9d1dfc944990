"""E57 XML sections that the e57 library must never read: a DTD (entity expansion, external entities), XML Schema
locations, a section that is not UTF-8, XML whose size, element count, depth or structure width is beyond the limits
(100,000 levels crash the library), and what would make the library read other counts or poses than the pre-check
saw: a data3D elsewhere than under the root, a record count that is not a decimal integer, a quaternion that is not a
unit one; and a Float precision it does not know. Each is a 400 naming the problem, found before the library opens
the file; files within the limits still read."""

from __future__ import annotations

import io
import re
import time

import numpy as np
import pye57
import pytest
from e57_xml import with_xml, xml_of

from service.formats import PointCloudFormatError, read_cloud
from service.formats import e57 as e57_reader
from service.formats.read import check_declared_count

XYZ = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32).astype(np.float64)
SPOT = b'<coordinateMetadata type="String"/>'  # an element of the root structure pye57 writes
DECLARATION = b'<?xml version="1.0" encoding="UTF-8"?>'
DEPTH, WIDTH, ELEMENTS = 64, 256, 100_000  # e57_reader.MAX_XML_DEPTH, MAX_STRUCTURE_CHILDREN, MAX_XML_ELEMENTS


@pytest.fixture(scope="module")
def e57(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("e57") / "a.e57"
    with pye57.E57(str(path), mode="w") as e57:
        e57.write_scan_raw({f"cartesian{axis}": np.ascontiguousarray(XYZ[:, k]) for k, axis in enumerate("XYZ")})
    return path.read_bytes()


def edited(data: bytes, old: bytes, new: bytes) -> bytes:
    xml = xml_of(data)
    assert old in xml
    return with_xml(data, xml.replace(old, new, 1))


def refused(data: bytes, *words: str) -> str:
    started = time.perf_counter()
    with pytest.raises(PointCloudFormatError) as caught:
        read_cloud(data, "a.e57", max_points=2_000_000)
    assert time.perf_counter() - started < 2
    assert caught.value.status == 400
    message = str(caught.value)
    assert message.startswith("a.e57: the E57 file's XML section"), message
    for word in words:
        assert word in message, message
    return message


def test_the_limits_are_those_the_reader_states() -> None:
    assert (e57_reader.MAX_XML_DEPTH, e57_reader.MAX_STRUCTURE_CHILDREN, e57_reader.MAX_XML_ELEMENTS) == (
        DEPTH,
        WIDTH,
        ELEMENTS,
    )
    assert e57_reader.MAX_XML_BYTES == 16 << 20


def test_rewritten_xml_within_the_limits_still_reads(e57) -> None:
    np.testing.assert_array_equal(read_cloud(with_xml(e57, xml_of(e57)), "a.e57"), XYZ)  # the helper's rebuild
    within = edited(
        e57, SPOT, b'<extra type="Structure">' + b"".join(b'<e%d type="Integer"/>' % k for k in range(9)) + b"</extra>"
    )
    np.testing.assert_array_equal(read_cloud(within, "a.e57"), XYZ)


def test_a_dtd_is_refused_before_its_entities_expand(e57) -> None:
    # ten entities of ten references each: 10 ** 5 copies of "AAAAAAAAAA" where a scan's description was
    entities = b'<!ENTITY a0 "AAAAAAAAAA">' + b"".join(
        b'<!ENTITY a%d "%s">' % (k, b"&a%d;" % (k - 1) * 10) for k in range(1, 6)
    )
    # every element and attribute declared: Xerces validates the document by its DTD
    names, attributes = (sorted(set(re.findall(pattern, xml_of(e57)))) for pattern in (rb"<(\w+)[\s/>]", rb" (\w+)=\""))
    listed = b" ".join(b"%s CDATA #IMPLIED" % name for name in attributes)
    declared = b"".join(b"<!ELEMENT %s ANY><!ATTLIST %s %s>" % (name, name, listed) for name in names)
    bomb = edited(e57, DECLARATION, DECLARATION + b"<!DOCTYPE e57Root [" + declared + entities + b"]>")
    bomb = with_xml(bomb, xml_of(bomb).replace(b"<![CDATA[pye57 v", b"&a5;<![CDATA[pye57 v", 1))
    refused(bomb, "document type declaration (<!DOCTYPE>)")
    external = edited(e57, DECLARATION, DECLARATION + b'<!DOCTYPE e57Root SYSTEM "file:///etc/hostname">')
    refused(external, "document type declaration")


@pytest.mark.parametrize("attribute", [b"schemaLocation", b"noNamespaceSchemaLocation"])
def test_a_schema_location_is_refused_not_fetched(e57, attribute: bytes) -> None:
    # a port nothing listens on: Xerces tried to connect to it ("unable to connect socket for URL")
    url = b"http://127.0.0.1:9/e57.xsd"
    value = b"http://www.astm.org/COMMIT/E57/2010-e57-v1.0 " + url if attribute == b"schemaLocation" else url
    root = b'<e57Root type="Structure"'
    schema = b' xmlns:s="http://www.w3.org/2001/XMLSchema-instance" s:%s="%s"' % (attribute, value)
    message = refused(edited(e57, root, root + schema), f"Schema instance attribute '{attribute.decode()}'")
    assert "127.0.0.1" not in message


def test_xml_in_another_encoding_than_utf8_is_refused(e57) -> None:
    xml = xml_of(e57).replace(DECLARATION, b'<?xml version="1.0" encoding="UTF-16"?>', 1)
    refused(with_xml(e57, xml.decode("utf-8").encode("utf-16")), "not UTF-8", "NUL bytes")
    latin = xml_of(e57).replace(DECLARATION, b'<?xml version="1.0" encoding="ISO-8859-1"?>', 1)
    refused(with_xml(e57, latin), "declares the encoding 'ISO-8859-1'")


def test_xml_nested_too_deep_is_refused(e57) -> None:
    depth = DEPTH
    within = edited(e57, SPOT, b'<d type="Structure">' * (depth - 3) + b"</d>" * (depth - 3))  # the spot is 2 deep
    assert len(read_cloud(within, "a.e57")) == len(XYZ)
    # 100,000 levels crashed the e57 library (a stack overflow, SIGSEGV); they took libE57Format 17 s
    refused(edited(e57, SPOT, b'<d type="Structure">' * depth + b"</d>" * depth), f"more than {depth} deep")


def test_a_structure_of_too_many_children_is_refused(e57) -> None:
    # 100,000 children of one structure took libE57Format 136 s (the e57 library 0.14 s)
    width = WIDTH + 1
    wide = b'<w type="Structure">' + b"".join(b'<c%d type="Integer"/>' % k for k in range(width)) + b"</w>"
    refused(edited(e57, SPOT, wide), f"a structure of more than {width - 1} children")
    vector = b'<v type="Vector" allowHeterogeneousChildren="1">' + b'<c type="Integer"/>' * width + b"</v>"
    assert len(read_cloud(edited(e57, SPOT, vector), "a.e57")) == len(XYZ)  # a vector's children are not named


def test_xml_of_too_many_elements_or_bytes_is_refused(e57) -> None:
    count = ELEMENTS
    many = b'<v type="Vector" allowHeterogeneousChildren="1">' + b'<c type="Integer"/>' * count + b"</v>"
    refused(edited(e57, SPOT, many), f"more than {count} elements")
    big = edited(
        e57,
        SPOT,
        b'<coordinateMetadata type="String"><![CDATA[%s]]></coordinateMetadata>' % (b"a" * (16 << 20)),
    )
    refused(big, f"at most {16 << 20} are read")


@pytest.mark.parametrize("offset", [2**63, 2**64 - 1, 10**12])
def test_an_xml_offset_beyond_the_file_is_refused_before_the_library_reads(e57, offset: int) -> None:
    data = bytearray(e57)
    data[24:32] = offset.to_bytes(8, "little")  # xmlPhysicalOffset (page 0's checksum now wrong)
    with pytest.raises(PointCloudFormatError, match=r"E57 file is cut short|a page's checksum") as caught:
        read_cloud(bytes(data), "a.e57")
    assert caught.value.status == 400


@pytest.mark.parametrize("count", ["\u00b2", "+50", " 50", "5e1", "-1", ""])
def test_a_record_count_that_is_not_a_decimal_integer_is_refused(e57, count: str) -> None:
    """The library parses ``+50`` as 50 (Rust's u64); the pre-check counted only ``str.isdigit()`` values, and
    ``int()`` of a superscript two, a digit to ``isdigit``, was a ValueError (a 500)."""
    data = edited(e57, b'recordCount="50"', b'recordCount="%s"' % count.encode())
    refused(data, "recordCount", "not a decimal integer")
    assert check_declared_count(io.BytesIO(data), "a.e57", 10) is None  # read_cloud's to name


@pytest.mark.parametrize("precision", ["Single", "singel", "", "double "])
def test_a_float_precision_other_than_single_or_double_is_refused_naming_the_field(e57, precision: str) -> None:
    """The library reads a Float field's ``precision`` as ``single`` or ``double`` exactly (none: ``double``) and
    refuses another value when it opens the file; the record-count check needs each field's bits, so it is refused
    in the parse, naming the field and the value."""
    data = edited(e57, b'precision="single"', b'precision="%s"' % precision.encode())
    refused(data, f"gives scan 0's field 'cartesianX' the Float precision {precision!r}", "'single' and 'double'")


def test_a_data3d_child_that_is_not_a_structure_is_skipped_as_the_library_skips_it(e57, tmp_path, capfd) -> None:
    """The library reads the data3D children of type Structure only: the parse counted every child, so a file whose
    one scan is of another type panicked in the library ("files contain pointclouds"), and another's points were
    counted against the limit without being read."""
    path = tmp_path / "two.e57"
    with pye57.E57(str(path), mode="w") as writer:
        for part in (XYZ[:20], XYZ[20:]):
            writer.write_scan_raw(
                {f"cartesian{axis}": np.ascontiguousarray(part[:, k]) for k, axis in enumerate("XYZ")}
            )
    two = edited(path.read_bytes(), b'<vectorChild type="Structure">', b'<vectorChild type="Integer">')  # the first
    np.testing.assert_allclose(read_cloud(two, "a.e57"), XYZ[20:])
    assert check_declared_count(io.BytesIO(two), "a.e57", 30) is None  # the 30 points read, not 50
    one = edited(e57, b'<vectorChild type="Structure">', b'<vectorChild type="Integer">')
    with pytest.raises(PointCloudFormatError, match=r"holds no scans") as caught:
        read_cloud(one, "a.e57")
    assert caught.value.status == 422
    assert "panicked" not in capfd.readouterr().err


def test_a_data3d_other_than_the_roots_is_refused(e57) -> None:
    """The library reads the first data3D in document order, anywhere; the pre-check counts the root's."""
    points = b'<points type="CompressedVector" fileOffset="48" recordCount="7"><prototype type="Structure"/></points>'
    nested = b'<x type="Structure"><data3D type="Vector"><vectorChild type="Structure">%s</vectorChild></data3D></x>'
    refused(edited(e57, SPOT, nested % points), "a data3D element other than the root's")


def test_a_pose_quaternion_that_is_not_a_unit_one_is_refused(e57, tmp_path) -> None:
    """The library does not normalise the quaternion: one of norm 2 read the scan 4 times larger."""
    path = tmp_path / "posed.e57"
    with pye57.E57(str(path), mode="w") as writer:
        columns = {f"cartesian{axis}": np.ascontiguousarray(XYZ[:, k]) for k, axis in enumerate("XYZ")}
        writer.write_scan_raw(columns, rotation=np.array([2.0, 0, 0, 0]), translation=np.zeros(3))
    with pytest.raises(PointCloudFormatError, match=r"scan 0's pose has a rotation quaternion of norm 2;") as caught:
        read_cloud(path.read_bytes(), "a.e57")
    assert caught.value.status == 400
    typed = edited(path.read_bytes(), b'<w type="Float">2</w>', b'<w type="Float">0.99999</w>')  # within 1e-4: read
    np.testing.assert_allclose(read_cloud(typed, "a.e57"), XYZ * 0.99999**2, rtol=1e-12)


@pytest.mark.parametrize(
    "value, what",
    [(b"<!-- c -->5", "a comment"), (b"5<!-- c -->1", "a comment"), (b"<?pi a?>5", "a processing instruction")],
)
def test_a_comment_inside_a_value_is_refused_as_the_library_reads_only_up_to_it(tmp_path, value, what) -> None:
    """The library read ``<x><!-- c -->5</x>`` as 0 and ``5<!-- c -->1`` as 5, where other readers read 5 and 51."""
    path = tmp_path / "posed.e57"
    with pye57.E57(str(path), mode="w") as writer:
        columns = {f"cartesian{axis}": np.ascontiguousarray(XYZ[:, k]) for k, axis in enumerate("XYZ")}
        writer.write_scan_raw(columns, rotation=np.array([1.0, 0, 0, 0]), translation=np.array([5.0, 0, 0]))
    posed = path.read_bytes()
    np.testing.assert_allclose(read_cloud(posed, "a.e57"), XYZ + np.array([5.0, 0, 0]), rtol=1e-12)
    between = edited(posed, b'<x type="Float">5</x>', b'<!-- c --><x type="Float">5</x><?pi a?>')  # not inside
    np.testing.assert_allclose(read_cloud(between, "a.e57"), XYZ + np.array([5.0, 0, 0]), rtol=1e-12)
    refused(edited(posed, b'<x type="Float">5</x>', b'<x type="Float">%s</x>' % value), what, "inside the value of <x>")


@pytest.mark.parametrize("value", [b"nan", b"1e400"])
def test_a_pose_translation_that_is_not_finite_is_refused_naming_the_pose(tmp_path, value) -> None:
    """It was read as NaN or infinite coordinates, and the 422 blamed the point rows."""
    path = tmp_path / "shifted.e57"
    with pye57.E57(str(path), mode="w") as writer:
        columns = {f"cartesian{axis}": np.ascontiguousarray(XYZ[:, k]) for k, axis in enumerate("XYZ")}
        writer.write_scan_raw(columns, rotation=np.array([1.0, 0, 0, 0]), translation=np.array([1.5, 2.5, 3.5]))
    refused(edited(path.read_bytes(), b'<x type="Float">1.5</x>', b'<x type="Float">' + value + b"</x>"),
            "scan 0's pose the translation", "not finite")


def test_a_scan_without_all_three_coordinates_is_refused_naming_what_it_has(e57) -> None:
    """It was refused as 'all points marked invalid (no return)', which the file does not say."""
    xml = xml_of(e57)
    z_field = re.search(rb'<cartesianZ [^>]*/>|<cartesianZ [^>]*>.*?</cartesianZ>', xml, re.S)
    assert z_field is not None
    refused(with_xml(e57, xml.replace(z_field.group(0), b"", 1)), "gives scan 0 no coordinates",
            "['cartesianX', 'cartesianY']")
