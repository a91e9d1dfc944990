"""E57 files with their XML section rewritten: E57 pages (1,020 bytes of data and a CRC-32C each) rebuilt
around the new XML, so that the file passes the page checksums and its XML reaches the reader."""

from __future__ import annotations

import struct

import numpy as np

PAGE, DATA = 1024, 1020
HEADER = struct.Struct("<8sIIQQQQ")  # signature, version major, minor, file length, XML offset, XML length, page size


def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint32)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1  # CRC-32C (Castagnoli), reflected
        table[byte] = crc
    return table


TABLE = _crc_table()


def _crc32c(pages: np.ndarray) -> np.ndarray:
    """``[P]`` CRC-32C of each row of ``pages [P, 1020]`` (uint8), all pages at once."""
    crc = np.full(len(pages), 0xFFFFFFFF, dtype=np.uint32)
    for k in range(pages.shape[1]):
        crc = TABLE[(crc ^ pages[:, k]) & 0xFF] ^ (crc >> np.uint32(8))
    return crc ^ np.uint32(0xFFFFFFFF)


def _logical(data: bytes) -> bytes:
    return np.frombuffer(data, dtype=np.uint8).reshape(-1, PAGE)[:, :DATA].tobytes()


def _paged(logical: bytes) -> bytes:
    logical += b"\0" * (-len(logical) % DATA)
    pages = np.frombuffer(logical, dtype=np.uint8).reshape(-1, DATA)
    out = np.zeros((len(pages), PAGE), dtype=np.uint8)
    out[:, :DATA] = pages
    out[:, DATA:] = np.frombuffer(_crc32c(pages).astype(">u4").tobytes(), dtype=np.uint8).reshape(-1, 4)
    return out.tobytes()


def xml_of(data: bytes) -> bytes:
    """The XML section of the E57 file ``data``."""
    _, _, _, _, offset, length, _ = HEADER.unpack_from(data)
    start = offset // PAGE * DATA + offset % PAGE
    return _logical(data)[start : start + length]


def with_xml(data: bytes, xml: bytes) -> bytes:
    """The E57 file ``data`` with ``xml`` in place of its XML section (the binary sections before it kept)."""
    signature, major, minor, _, offset, _, page = HEADER.unpack_from(data)
    logical = bytearray(_logical(data)[: offset // PAGE * DATA + offset % PAGE]) + xml
    length = (len(logical) + DATA - 1) // DATA * PAGE
    HEADER.pack_into(logical, 0, signature, major, minor, length, offset, len(xml), page)
    return _paged(bytes(logical))
