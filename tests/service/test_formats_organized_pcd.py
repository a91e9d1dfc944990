"""Organized PCD files (``HEIGHT`` > 1, as PCL, ROS and depth cameras write them): points whose x, y and z are all
NaN are missing returns, left out on read in every encoding, from a file, an HTTP upload and the CLI; any other NaN
or Inf, an organized cloud of missing returns only, and NaN rows of an unorganized file stay a 422 naming them.

The files are written by pypcd4 (a real writer of the format) or byte by byte as PCL's ``pcl::io::savePCDFileASCII``
writes a ``PointXYZ`` grid."""

from __future__ import annotations

import base64
import json
import tracemalloc
from pathlib import Path

import numpy as np
import pypcd4
import pytest
from api_server import MODEL, assert_error, synthetic_pair
from typer.testing import CliRunner

from service.cli import app
from service.formats import InvalidPointsError, TooManyPointsError, read_cloud

ENCODINGS = {"ascii": pypcd4.Encoding.ASCII, "binary": pypcd4.Encoding.BINARY,
             "binary_compressed": pypcd4.Encoding.BINARY_COMPRESSED}
HEIGHT, WIDTH = 24, 40  # a small depth image's grid
OPTIONS = {"model": MODEL, "rotation_search": "false"}


def organized(points: np.ndarray, height: int, width: int, seed: int = 0) -> np.ndarray:
    """``points [K, 3]`` in their order at seeded random pixels of a ``height`` x ``width`` grid, every other pixel a
    missing return: ``[height * width, 3]`` float32 with NaN rows."""
    grid = np.full((height * width, 3), np.nan, dtype=np.float32)  # [H * W, 3]
    pixels = np.sort(np.random.default_rng(seed).choice(height * width, len(points), replace=False))  # [K]
    grid[pixels] = points
    return grid


def write_pcd(path: Path, grid: np.ndarray, height: int, width: int, encoding: str) -> Path:
    """``grid [height * width, 3]`` as an organized PCD of fields x y z rgb (a depth camera's ``PointXYZRGB``),
    written by pypcd4."""
    rgb = pypcd4.PointCloud.encode_rgb(np.full((len(grid), 3), 200, dtype=np.uint8))  # [H * W] packed as float32
    cloud = pypcd4.PointCloud.from_xyzrgb_points(np.column_stack([grid, rgb]))
    cloud = pypcd4.PointCloud(cloud.metadata.derive(width=width, height=height), cloud.pc_data)
    cloud.save(path, encoding=ENCODINGS[encoding])
    return path


def frame(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A ``HEIGHT`` x ``WIDTH`` grid ``[H * W, 3]`` with 40% missing returns, and its valid points ``[K, 3]``."""
    valid = np.random.default_rng(seed).normal(size=(int(0.6 * HEIGHT * WIDTH), 3)).astype(np.float32)  # [K, 3]
    return organized(valid, HEIGHT, WIDTH, seed), valid


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_missing_returns_of_an_organized_pcd_are_left_out_in_every_encoding(tmp_path: Path, encoding: str) -> None:
    grid, valid = frame()
    path = write_pcd(tmp_path / "depth.pcd", grid, HEIGHT, WIDTH, encoding)
    assert f"HEIGHT {HEIGHT}\n".encode() in path.read_bytes()[:300]
    read = read_cloud(path)
    np.testing.assert_array_equal(read, valid.astype(np.float64))  # the valid points, in the file's order
    with pytest.raises(TooManyPointsError):  # the point limit counts the file's points, missing returns included
        read_cloud(path, max_points=len(valid))


def test_a_pcl_ascii_organized_frame_reads_its_valid_points(tmp_path: Path) -> None:
    # pcl::io::savePCDFileASCII of an organized pcl::PointCloud<pcl::PointXYZ>: NaN written as "nan"
    grid, valid = frame(1)
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
              f"COUNT 1 1 1\nWIDTH {WIDTH}\nHEIGHT {HEIGHT}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(grid)}\nDATA ascii\n")
    body = "".join(" ".join("nan" if np.isnan(v) else f"{v:.9g}" for v in row) + "\n" for row in grid)
    (tmp_path / "frame.pcd").write_bytes((header + body).encode())
    np.testing.assert_array_equal(read_cloud(tmp_path / "frame.pcd"), valid.astype(np.float64))


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_other_nan_or_inf_of_an_organized_pcd_is_refused_naming_it(tmp_path: Path, encoding: str,
                                                                   value: float) -> None:
    grid, _ = frame()
    valid_rows = np.flatnonzero(~np.isnan(grid).all(axis=1))  # [K]
    first, second = valid_rows[[10, 20]]
    grid[first, 1] = value  # one coordinate of a valid point: not a missing return
    grid[second] = value if np.isinf(value) else [1.0, np.nan, np.nan]
    path = write_pcd(tmp_path / "depth.pcd", grid, HEIGHT, WIDTH, encoding)
    where = rf"first at index {first} \(row {first // WIDTH}, column {first % WIDTH}\)"
    with pytest.raises(InvalidPointsError, match=rf"depth.pcd: 2 point\(s\) of the organized cloud \(40 x 24\) "
                                                 rf"with NaN/Inf .*{where}"):
        read_cloud(path)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_an_organized_pcd_of_missing_returns_only_is_refused(tmp_path: Path, encoding: str) -> None:
    grid = np.full((HEIGHT * WIDTH, 3), np.nan, dtype=np.float32)
    path = write_pcd(tmp_path / "dark.pcd", grid, HEIGHT, WIDTH, encoding)
    with pytest.raises(InvalidPointsError, match=r"dark.pcd: the organized cloud \(40 x 24\) has no valid point: "
                                                 rf"all {HEIGHT * WIDTH} are missing returns"):
        read_cloud(path)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_nan_rows_of_an_unorganized_pcd_stay_refused(tmp_path: Path, encoding: str) -> None:
    grid, _ = frame()  # the same points in one row: no grid whose pixels the NaN rows keep
    path = write_pcd(tmp_path / "flat.pcd", grid, 1, len(grid), encoding)
    first = int(np.flatnonzero(np.isnan(grid).all(axis=1))[0])
    with pytest.raises(InvalidPointsError, match=rf"flat.pcd: {int(np.isnan(grid).all(axis=1).sum())} point\(s\) "
                                                 rf"with NaN/Inf .* first at index {first}; leave such rows out"):
        read_cloud(path)


def test_leaving_missing_returns_out_holds_no_second_copy(tmp_path: Path) -> None:
    """A 2,000,000-point binary frame (1000 x 2000, 40% missing returns) read with at most 16 MiB above its one
    ``[N, 3]`` float64 array (46 MiB): the valid points are moved up within it, a block at a time."""
    height, width = 1000, 2000
    valid = np.random.default_rng(2).normal(size=(int(0.6 * height * width), 3)).astype(np.float32)  # [K, 3]
    grid = organized(valid, height, width, 2)
    path = write_pcd(tmp_path / "big.pcd", grid, height, width, "binary")
    del grid
    tracemalloc.start()
    try:
        read = read_cloud(path)
        peak = tracemalloc.get_traced_memory()[1] - height * width * 3 * 8
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(read, valid.astype(np.float64))
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MiB above the cloud"


# -- through a real server and the CLI ----------------------------------------------------------------
@pytest.fixture(scope="module")
def pair_files(tmp_path_factory) -> dict[str, tuple[Path, Path]]:
    """The test pair as ``.npy`` and as organized PCD frames (60 x 20 grids, 700 valid pixels) in each encoding."""
    folder = tmp_path_factory.mktemp("organized")
    pair = synthetic_pair(3)
    files = {"npy": (folder / "source.npy", folder / "target.npy")}
    np.save(files["npy"][0], pair.source)
    np.save(files["npy"][1], pair.target)
    for encoding in ENCODINGS:
        files[encoding] = tuple(write_pcd(folder / f"{name}-{encoding}.pcd", organized(points, 20, 60, seed), 20, 60,
                                          encoding)
                                for seed, (name, points) in enumerate((("source", pair.source),
                                                                       ("target", pair.target))))
    return files


def post(client, route: str, source: Path, target: Path):
    files = {"source": (source.name, source.read_bytes()), "target": (target.name, target.read_bytes())}
    return client.post(route, files=files, data=OPTIONS, timeout=120)


def test_organized_pcd_uploads_give_the_pose_of_their_valid_points(client, pair_files) -> None:
    reference = post(client, "/v1/register", *pair_files["npy"])
    assert reference.status_code == 200, reference.text
    for encoding in ENCODINGS:
        response = post(client, "/v1/register", *pair_files[encoding])
        assert response.status_code == 200, (encoding, response.text)
        assert_same_pose(response.json(), reference.json())
        if encoding != "ascii":  # the same float32 values (pypcd4's ASCII keeps 10 decimals): the same matches
            assert response.json()["correspondences"] == reference.json()["correspondences"], encoding
    view = post(client, "/v1/register/view", *pair_files["binary_compressed"])
    assert view.status_code == 200, view.text
    pair = synthetic_pair(3)
    for name, points in (("source", pair.source), ("target", pair.target)):
        display = view.json()["display"][name]
        assert display["points"] == len(points), name  # the points read: missing returns left out
        shown = np.frombuffer(base64.b64decode(display["xyz"]), dtype="<f4").reshape(-1, 3)  # [n, 3]
        np.testing.assert_array_equal(shown, points)


def test_bad_organized_pcd_uploads_are_a_422_naming_the_file(client, tmp_path: Path) -> None:
    grid, _ = frame()
    target = write_pcd(tmp_path / "target.pcd", grid, HEIGHT, WIDTH, "binary")
    grid[int(np.flatnonzero(~np.isnan(grid).all(axis=1))[0]), 2] = np.inf
    partial = write_pcd(tmp_path / "partial.pcd", grid, HEIGHT, WIDTH, "binary")
    assert_error(post(client, "/v1/register", partial, target), 422, "partial.pcd", "1 point(s) of the organized cloud",
                 "NaN/Inf", "row 0")
    dark = write_pcd(tmp_path / "dark.pcd", np.full_like(grid, np.nan), HEIGHT, WIDTH, "binary_compressed")
    assert_error(post(client, "/v1/register", dark, target), 422, "dark.pcd", "no valid point")


def test_the_cli_registers_organized_pcd_frames(pair_files) -> None:
    runner = CliRunner()
    reference = runner.invoke(app, ["register", *map(str, pair_files["npy"]), "--model", MODEL, "--json"])
    result = runner.invoke(app, ["register", *map(str, pair_files["ascii"]), "--model", MODEL, "--json"])
    assert result.exit_code == 0, result.output
    record, expected = (json.loads(r.stdout[r.stdout.index("{"):]) for r in (result, reference))
    assert_same_pose(record, expected)


def assert_same_pose(record: dict, reference: dict) -> None:
    """The same rotation and translation to 1e-9 (the ASCII file's points differ from the ``.npy``'s in their last
    float32 digit at most)."""
    for key in ("rotation", "translation"):
        np.testing.assert_allclose(record[key], reference[key], rtol=0, atol=1e-9, err_msg=key)
