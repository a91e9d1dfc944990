"""Specification of the early refusal of oversized uploads: a file whose header declares more points than
``max_file_points`` (PLY, PCD, LAS/LAZ, E57, PTS, PTX, .npy, .npz) is a 413 before the request waits for a worker, the
same 413 the decoder answers, so a busy server refuses it at once instead of a 504 when its deadline passes in the
queue; files within the limit, and text files (counted only while read), still queue and are decoded by a worker,
which stays the authority (``service.formats.read.check_declared_count``).

The server is real (uvicorn in a thread of this process, the bundled model, real HTTP) with one worker and a short
deadline; a route added to the app holds that worker (a job that waits on an event, its deadline stopped as a decode's
is) for as long as a test needs, without using a CPU.
"""

from __future__ import annotations

import io
import json
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
from api_server import Server, assert_error, held_worker_server, wait_for

from service.formats import TooManyPointsError, read_cloud, write_cloud
from service.formats.read import HEADER_COUNTS, check_declared_count

LIMIT = 1_000  # the server's max_file_points
DEADLINE_S = 0.5  # its timeout_s: a request that waits for the held worker is a 504 after this long
HEADER_FORMATS = (".npy", ".npz", ".ply", ".pcd", ".las", ".laz", ".e57", ".pts", ".ptx")
FAST = {"iterations": "1", "keypoints": "16"}
RNG = np.random.default_rng(0)
SMALL = RNG.normal(size=(300, 3))  # [300, 3]
BIG = RNG.normal(size=(LIMIT + 1, 3))  # [1001, 3]


def cloud_file(points: np.ndarray, suffix: str, folder: Path) -> bytes:
    """``points [N, 3]`` as a file of ``suffix`` (LAS/LAZ through laspy, E57 through pye57, PTS and PTX as text, the
    others through ``write_cloud``)."""
    path = folder / f"cloud{suffix}"
    rows = "".join(f"{x:.17g} {y:.17g} {z:.17g} 0.5\n" for x, y, z in points)
    if suffix == ".pts":
        path.write_text(f"{len(points)}\n{rows}")
    elif suffix == ".ptx":  # a scan of one row
        path.write_text(f"{len(points)}\n1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n{rows}")
    elif suffix == ".e57":
        import pye57

        with pye57.E57(str(path), mode="w") as e57:
            e57.write_scan_raw({f"cartesian{axis}": np.ascontiguousarray(points[:, k]) for k, axis in enumerate("XYZ")})
    elif suffix in (".las", ".laz"):
        import laspy

        header = laspy.LasHeader(point_format=3, version="1.2")
        header.scales = [0.001] * 3
        las = laspy.LasData(header)
        las.x, las.y, las.z = points.T
        las.write(path)
    else:
        write_cloud(path, points)
    return path.read_bytes()


def npy(points: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, points)
    return buf.getvalue()


# -- the header check beside the reader ---------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", HEADER_FORMATS)
def test_an_oversized_header_is_refused_as_the_reader_refuses_it_and_the_position_is_kept(suffix, tmp_path):
    data = cloud_file(BIG, suffix, tmp_path)
    f = io.BytesIO(data)
    with pytest.raises(TooManyPointsError) as early:
        check_declared_count(f, "source (c)", LIMIT)
    assert f.tell() == 0
    with pytest.raises(TooManyPointsError) as decoded:
        read_cloud(io.BytesIO(data), "source (c)", LIMIT)
    expected = f"source (c): has {LIMIT + 1} points; the limit is {LIMIT} per cloud"
    assert str(early.value) == str(decoded.value) == expected
    assert (early.value.count, early.value.limit) == (LIMIT + 1, LIMIT)
    check_declared_count(f, "source (c)", LIMIT + 1)  # within the limit: nothing said
    assert f.tell() == 0


def test_text_and_unreadable_headers_are_left_to_the_reader(tmp_path):
    """Text has no count before it is read; a damaged header is the reader's to describe (400), not this check's."""
    assert "text" not in HEADER_COUNTS
    check_declared_count(io.BytesIO(cloud_file(BIG, ".xyz", tmp_path)), "c", LIMIT)
    for broken in (b"\x93NUMPY\x01\x00garbage", b"ply\nformat ascii 1.0\nelement vertex 5000\n", b"LASF" + bytes(40)):
        check_declared_count(io.BytesIO(broken), "c", LIMIT)


def test_a_header_that_lies_is_still_the_readers_to_judge(tmp_path):
    """Declaring more rows than the data holds is refused for its declared size by both, as before; declaring fewer
    passes the check, and the reader reads no more than the header declares."""
    short = npy(BIG)[:200]  # the header of 1,001 rows, almost none of their bytes
    with pytest.raises(TooManyPointsError):
        check_declared_count(io.BytesIO(short), "c", LIMIT)
    with pytest.raises(TooManyPointsError):
        read_cloud(short, "c", LIMIT)
    header = npy(SMALL[:10])  # a header of 10 rows...
    understated = header[: len(header) - 10 * 24] + BIG.tobytes()  # ...followed by 1,001 rows
    check_declared_count(io.BytesIO(understated), "c", LIMIT)
    assert read_cloud(understated, "c", LIMIT).shape == (10, 3)


# -- a real server whose one worker is held -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def held() -> Iterator[tuple[Server, object, threading.Event]]:
    """One worker, four places in the queue, a 0.5 s deadline, at most 1,000 points per file; ``POST /test/hold``
    holds the worker until the event is set. Yields the server, its limiter and the event."""
    server, limiter, release = held_worker_server(timeout_s=DEADLINE_S, max_file_points=LIMIT)
    yield server, limiter, release
    release.set()
    server.stop()


@contextmanager
def releasing(release: threading.Event) -> Iterator[None]:
    """The held worker released on the way out, whatever happened (a failed assertion too)."""
    try:
        yield
    finally:
        release.set()


def post(server: Server, path: str, **kwargs) -> tuple[httpx.Response, float]:
    """The answer and the seconds it took."""
    with server.client() as client:
        started = time.perf_counter()
        response = client.post(path, **kwargs)
        return response, time.perf_counter() - started


def test_an_oversized_upload_is_413_at_once_on_a_busy_server_and_a_right_sized_one_still_queues(held, tmp_path):
    """While the only worker is busy, an upload over max_file_points was queued and answered 504 once the deadline
    passed; it is now refused at once, on every route that takes files and for each format with a header, holding no
    place in the queue. A right-sized upload still waits for the worker (504 here), and registers once it is free."""
    server, limiter, release = held
    big, small = npy(BIG), npy(SMALL)
    eye = json.dumps(np.eye(4).tolist())
    with ThreadPoolExecutor(1) as pool, releasing(release):
        holder = pool.submit(post, server, "/test/hold")
        wait_for(lambda: limiter.running == 1, what="the worker held")
        cases = [
            ("/v1/register", {"source": ("s.npy", small), "target": ("big.npy", big)}, {}, "target (big.npy)"),
            ("/v1/register/view", {"source": ("big.npy", big), "target": ("t.npy", small)}, {}, "source (big.npy)"),
            ("/v1/register/aligned", {"source": ("big.npy", big)}, {"transform": eye}, "source (big.npy)"),
        ]
        for suffix in HEADER_FORMATS[1:]:
            files = {"source": (f"big{suffix}", cloud_file(BIG, suffix, tmp_path)), "target": ("t.npy", small)}
            cases.append(("/v1/register", files, {}, f"source (big{suffix})"))
        for path, files, data, named in cases:
            response, took = post(server, path, files=files, data=data)
            assert_error(response, 413, named, f"has {LIMIT + 1} points", f"limit is {LIMIT}", "MFGNET_MAX_FILE_POINTS")
            assert took < DEADLINE_S, (path, named, took)
            assert limiter.taken == 1  # the holder's slot only: the refused request's is freed
        right_sized = {"source": ("s.npy", small), "target": ("t.npy", small)}
        response, took = post(server, "/v1/register", files=right_sized, data=FAST)
        assert_error(response, 504, "MFGNET_TIMEOUT_S")  # it waited in the queue for the worker, as before
        assert took >= DEADLINE_S
        text = {"source": ("big.xyz", cloud_file(BIG, ".xyz", tmp_path)), "target": ("t.npy", small)}
        response, _ = post(server, "/v1/register", files=text)
        assert_error(response, 504, "MFGNET_TIMEOUT_S")  # text: counted only once read, by the worker
        release.set()
        assert holder.result()[0].status_code == 200
    wait_for(lambda: limiter.taken == 0, what="the slots freed")
    response, _ = post(server, "/v1/register", files=right_sized, data=FAST)
    assert response.status_code == 200, response.text
    response, _ = post(server, "/v1/register", files=text)
    assert_error(response, 413, "source (big.xyz)", f"limit is {LIMIT}", "MFGNET_MAX_FILE_POINTS")  # the decoder's
