"""Point-cloud files as scanners and their software write them, with the libraries users have (plyfile, pypcd4,
laspy + lazrs, pye57, numpy): a coloured PLY mesh, a PCD with intensity, normals and packed colour, a LAS survey with
a CRS VLR, a terrestrial scanner's E57 project of posed scans with intensity and colour, and the arrays machine
learning code keeps (an ``.npy`` of x, y, z, normals and intensity; a deflated ``.npz`` of points, colours and
labels). Seeded. ``bench.server_memory --aligned`` uploads them; the tests of the aligned file
(``mfgnet register --write-aligned``, ``POST /v1/register/aligned``) compare what comes back against them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

PLY_NORMALS, PCD_NORMALS = ("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z")
UTM_OFFSETS = (512_000.0, 4_123_000.0, 100.0)  # a survey's offsets: UTM zone 32N eastings and northings


def unit_normals(n: int, seed: int = 1) -> np.ndarray:
    """``n`` seeded unit vectors ``[n, 3]``."""
    turned = np.random.default_rng(seed).normal(size=(n, 3))
    return turned / np.linalg.norm(turned, axis=1, keepdims=True)  # [n, 3] unit


def coloured_ply(path: Path, xyz: np.ndarray, text: bool = False) -> np.ndarray:
    """A mesh at ``xyz [n, 3]``: float x, y, z, normals, uchar colours, a float quality; 200 faces of 3 and 4
    corners; ASCII where ``text``, else binary little endian. Returns the vertex records."""
    import plyfile

    rng = np.random.default_rng(2)
    n = len(xyz)
    names = ("x", "y", "z", *PLY_NORMALS)
    vertex = np.empty(
        n,
        dtype=[*((name, "<f4") for name in names), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("quality", "<f4")],
    )
    columns = np.column_stack([xyz, unit_normals(n)])  # [n, 6]
    for axis, name in enumerate(names):
        vertex[name] = columns[:, axis]
    for name in ("red", "green", "blue"):
        vertex[name] = rng.integers(0, 256, n)
    vertex["quality"] = rng.random(n)
    faces = np.empty(200, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [rng.integers(0, n, 3 + k % 2).astype(np.int32) for k in range(200)]
    elements = [plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(faces, "face")]
    plyfile.PlyData(elements, text=text, byte_order="<", comments=["scanner X"]).write(str(path))
    return vertex


def pcd_with_fields(path: Path, xyz: np.ndarray, encoding: str = "binary") -> np.ndarray:
    """x, y, z (``xyz [n, 3]``), intensity, normals and a packed rgb float (PCL's layout) in ``encoding`` (``ascii``,
    ``binary`` or ``binary_compressed``); returns the records."""
    import pypcd4

    rng = np.random.default_rng(3)
    n = len(xyz)
    fields = ("x", "y", "z", "intensity", *PCD_NORMALS, "rgb")
    values = np.column_stack([xyz, rng.integers(0, 4, n), unit_normals(n), np.zeros(n)]).astype(np.float32)
    cloud = pypcd4.PointCloud.from_points(values, fields, (np.float32,) * len(fields))
    cloud.pc_data["rgb"] = pypcd4.PointCloud.encode_rgb(rng.integers(0, 4, (n, 3)).astype(np.uint8) * 60)
    if encoding == "ascii":  # pypcd4's own ASCII writer prints %.10f: packed colours would read back as 0
        with open(path, "wb") as f:
            f.write(cloud.metadata.compose_header(data=pypcd4.Encoding.ASCII).encode())
            np.savetxt(f, cloud.pc_data, fmt="%.9g")
    else:
        cloud.save(path, encoding=pypcd4.Encoding(encoding))
    return cloud.pc_data


def survey_las(path: Path, xyz: np.ndarray, offsets: tuple[float, float, float] = UTM_OFFSETS) -> None:
    """A LAS 1.2 point format 3 file of ``xyz [n, 3]`` at millimetre scale with ``offsets``, colours,
    classification, GPS time and a WKT CRS VLR (compressed where ``path`` ends in .laz)."""
    import laspy

    rng = np.random.default_rng(4)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = np.full(3, 0.001), np.asarray(offsets)
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr('PROJCS["WGS 84 / UTM zone 32N"]'))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    n = len(xyz)
    las.intensity = rng.integers(0, 65535, n)
    las.classification = rng.integers(0, 10, n)
    las.gps_time = rng.random(n) * 1e5
    for name in ("red", "green", "blue"):
        setattr(las, name, rng.integers(0, 65535, n))
    las.write(str(path))


def tls_e57(path: Path, xyz: np.ndarray, scans: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
    """An E57 project as a terrestrial scanner's software exports it (pye57, libE57Format): ``xyz [n, 3]`` split into
    ``scans`` scans of consecutive rows, each in its own frame with a pose (a turn about z and a shift, as a tripod's
    setups stand), float32 coordinates and intensity, 8-bit colour. Returns each scan's pose (quaternion w, x, y, z;
    translation)."""
    import pye57

    rng = np.random.default_rng(5)
    poses = []
    writer = pye57.E57(str(path), mode="w")
    try:
        for number, part in enumerate(np.array_split(xyz, scans)):
            angle = 0.7 * number  # about z
            pose = (np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]), np.array([10.0 * number, -3.0, 1.5]))
            data = {f"cartesian{axis}": np.ascontiguousarray(part[:, k]) for k, axis in enumerate("XYZ")}
            data["intensity"] = rng.random(len(part))
            for name in ("colorRed", "colorGreen", "colorBlue"):
                data[name] = rng.integers(0, 256, len(part)).astype(np.uint8)
            writer.write_scan_raw(data, name=f"Setup {number + 1}", rotation=pose[0], translation=pose[1])
            poses.append(pose)
    finally:
        writer.close()
    return poses


def ml_npy(path: Path, xyz: np.ndarray) -> np.ndarray:
    """A float32 ``[n, 7]`` array of ``xyz [n, 3]``, unit normals and an intensity in [0, 1), as point-cloud learning
    code keeps its samples; returns it."""
    rows = np.column_stack([xyz, unit_normals(len(xyz)), np.random.default_rng(6).random(len(xyz))])
    array = rows.astype(np.float32)  # [n, 7]
    np.save(path, array)
    return array


def labelled_npz(path: Path, xyz: np.ndarray) -> dict[str, np.ndarray]:
    """A deflated ``.npz`` (``np.savez_compressed``) of float32 ``points [n, 3]``, uint8 ``colors [n, 3]`` and int32
    per-point ``labels [n]`` (13 classes, as a segmentation set's); returns its arrays."""
    rng = np.random.default_rng(7)
    arrays = {
        "points": xyz.astype(np.float32),
        "colors": rng.integers(0, 256, (len(xyz), 3)).astype(np.uint8),
        "labels": rng.integers(0, 13, len(xyz)).astype(np.int32),
    }
    np.savez_compressed(path, **arrays)
    return arrays
