"""The browser page: ``GET /`` (static files from ``service/web``), ``POST /v1/register/view`` (a registration
plus decimated display clouds) and ``POST /v1/register/aligned`` (the uploaded source moved by a pose: a file of
any format the service reads comes back as itself, every other field kept: :func:`service.formats.moved.write_moved`;
an E57 file with every scan's and image's pose composed with the transform, its points, images and other fields copied
as they are: :mod:`service.formats.moved_e57`).

Uploads go through the reader and limits of ``POST /v1/register`` (:func:`service.api.bodies.decode_upload`: any
format of :mod:`service.formats`, found from the content, up to ``max_file_points`` per cloud). Display clouds
are float32 little-endian ``[n, 3]`` rows, base64 in the JSON, at most :data:`DISPLAY_CAP` points per cloud (a
seeded random subset when a cloud has more).
"""

from __future__ import annotations

import asyncio
import base64
import json
import shutil
import tempfile
from collections.abc import AsyncIterator, Callable
from pathlib import Path, PurePath
from typing import Any, BinaryIO
from urllib.parse import quote

import numpy as np
from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.responses import FileResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from service.api import bodies
from service.api.deps import get_runner, get_settings, refuse_query_on_post, require_api_key
from service.api.errors import APIError, TempStorageError, error_docs
from service.api.middleware import ABORT_CONNECTION, DROPPED_CLIENT
from service.api.responses import RenderedJSON
from service.api.routes.register import _MULTIPART_SCHEMA
from service.api.runner import register_response
from service.api.schemas import RegisterResponse
from service.api.security_headers import page_policy
from service.errors import InputError
from service.formats import PointCloudFormatError
from service.formats.moved import KEPT_FORMATS, own_suffix, source_format, write_moved
from service.registrar import check_transform

WEB_DIR = Path(__file__).resolve().parents[2] / "web"  # service/web: index.html, page.js, page.css
DISPLAY_CAP = 100_000  # points per cloud sent to the page
DISPLAY_SEED = 0
DISPLAY_FAR = 1.0e4  # a coordinate beyond this: display rows relative to their box (as service.client recentres)
# Nothing loaded from elsewhere, and no other site frames the page.
PAGE_POLICY = {"Content-Security-Policy": page_policy("default-src 'self'; img-src 'self' data: blob:")}
OCTET_STREAM = "application/octet-stream"
# The aligned download's media type by its extension: LAS, LAZ and CSV have IANA types; PLY, PCD, NPY and NPZ have
# none; XYZ, TXT, PTS and PTX are plain text.
ALIGNED_MEDIA_TYPES = {
    ".ply": OCTET_STREAM,
    ".pcd": OCTET_STREAM,
    ".las": "application/vnd.las",
    ".laz": "application/vnd.laszip",
    ".csv": "text/csv",
    ".txt": "text/plain",
    ".xyz": "text/plain",
    ".pts": "text/plain",
    ".ptx": "text/plain",
    ".e57": "model/e57",  # its IANA media type
    ".npy": OCTET_STREAM,
    ".npz": OCTET_STREAM,
}
STREAM_CHUNK_BYTES = 1 << 16  # each send must drain within MFGNET_BODY_TIMEOUT_S: ~4.4 KiB/s at the default

page_router = APIRouter(include_in_schema=False)
router = APIRouter(prefix="/v1", tags=["page"], dependencies=[Depends(require_api_key), Depends(refuse_query_on_post)])


@page_router.get("/")
async def index() -> FileResponse:
    """The registration page (offline: every script and style comes from this server)."""
    return FileResponse(WEB_DIR / "index.html", media_type="text/html", headers=PAGE_POLICY)


# -- upload ---------------------------------------------------------------------------------------
def _json_field(text: str, name: str) -> Any:
    try:
        return json.loads(text)
    except (ValueError, RecursionError):  # RecursionError: nested too deep
        raise APIError(422, f"invalid request: {name}: expected a JSON 4x4 array") from None


# -- display clouds -------------------------------------------------------------------------------
def decimated_rows(points: np.ndarray, cap: int = DISPLAY_CAP) -> np.ndarray:
    """At most ``cap`` rows of ``points [N, 3]`` (a seeded random subset, in file order), as they are."""
    if len(points) > cap:
        keep = np.sort(np.random.default_rng(DISPLAY_SEED).choice(len(points), cap, replace=False))
        points = points[keep]
    return points


def display_origin(points: np.ndarray) -> np.ndarray:
    """``[3]`` the point the display rows of ``points [N, 3]`` are relative to: the centre of their bounding box,
    rounded to whole units, where a coordinate lies beyond ``DISPLAY_FAR`` (float32 would round a map's UTM
    coordinates by decimetres); else the origin (the rows are the caller's own)."""
    if not len(points) or np.abs(points).max() <= DISPLAY_FAR:
        return np.zeros(3)
    return np.round((points.min(axis=0) + points.max(axis=0)) / 2)


def display_cloud(points: np.ndarray) -> dict[str, Any]:
    rows = decimated_rows(points)  # [n, 3] float64
    origin = display_origin(rows)
    shown = np.ascontiguousarray(rows - origin, dtype="<f4")  # [n, 3]
    return {"points": len(points), "shown": len(shown), "origin": origin.tolist(),
            "xyz": base64.b64encode(shown.tobytes()).decode("ascii")}


class DisplayCloud(BaseModel):
    points: int = Field(
        description="Points read from the uploaded cloud (an organized PCD's missing returns left out)."
    )
    shown: int = Field(description=f"Points sent for display: all, or {DISPLAY_CAP} chosen at random.")
    origin: list[float] = Field(description="The point the rows are relative to (caller's units and frame): [0, 0, 0], "
                                "or the centre of the cloud's box where float32 would round its coordinates.")
    xyz: str = Field(description="base64 of float32 little-endian [shown, 3] rows, caller's units, relative to origin.")


class Display(BaseModel):
    cap: int = Field(description="Most points per cloud sent for display.")
    source: DisplayCloud = Field(description="The source as uploaded (before the pose).")
    target: DisplayCloud = Field(description="The target as uploaded.")


class ViewResponse(BaseModel):
    result: RegisterResponse = Field(description="Exactly what POST /v1/register answers for the same upload.")
    display: Display = Field(description="Decimated copies of both clouds for drawing (caller's units and frame).")


_ALIGNED_SCHEMA = {
    "type": "object",
    "required": ["source", "transform"],
    "properties": {
        "source": {
            "type": "string",
            "format": "binary",
            "description": ("Point-cloud file [N, 3] in any format the service reads; it comes back in its own format, "
                            "moved (PLY, PCD, LAS/LAZ, E57, PTX, PTS, XYZ/TXT/CSV, NPY, NPZ)."),
        },
        "transform": {"type": "string", "description": "JSON 4x4 rigid src_to_tgt matrix."},
    },
}


def _multipart(schema: dict) -> dict:
    return {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": schema}}}}


# -- routes ---------------------------------------------------------------------------------------
@router.post(
    "/register/view",
    response_model=ViewResponse,
    summary="Register two uploaded files and return display clouds (the page's call)",
    description="Multipart form as POST /v1/register (files `source`, `target` in any supported point-cloud "
    f"format, options as fields). Answers the registration plus at most {DISPLAY_CAP} points per cloud, "
    "float32, for drawing; the aligned source is `source @ rotation.T + translation`.",
    openapi_extra=_multipart(_MULTIPART_SCHEMA),
    responses=error_docs(400, 401, 404, 408, 413, 415, 422, 503, 504),
)
async def register_view(request: Request) -> RenderedJSON:
    settings, runner = get_settings(request), get_runner(request)
    bodies.require_media_type(request, bodies.MULTIPART)
    with runner.admit() as slot:
        form = await bodies.read_register_form(request)  # the same reader and limits as POST /v1/register
        await bodies.refuse_oversized_uploads(form, settings.max_file_points)

        def decode() -> bodies.Pair:
            return bodies.register_pair_from_form(form, settings.max_file_points)

        def work(pair: bodies.Pair):
            entry, result = runner.register_one(pair)
            display = {"cap": DISPLAY_CAP, "source": display_cloud(pair.source), "target": display_cloud(pair.target)}
            return entry, pair, result, display

        (entry, pair, result, display), queue_ms = await runner.run(slot, work, request, decode)
    runner.observe(entry, result, queue_ms)
    return RenderedJSON({"result": register_response(entry, pair, result, queue_ms), "display": display})


_BINARY = {"schema": {"type": "string", "format": "binary"}}


@router.post(
    "/register/aligned",
    response_class=Response,
    summary="The uploaded source moved by a pose, in its own format",
    description="Multipart form: file `source` (any supported format) and field `transform`, a JSON 4x4 rigid "
    "src_to_tgt matrix (e.g. a registration's `transform`). Every point becomes `R @ p + t`. A PLY, PCD, LAS/LAZ, "
    "XYZ/CSV/TXT, PTS, PTX, NPY or NPZ source comes back as that file moved, named `<stem>_aligned.<its extension>` (a "
    "text source named otherwise: `.txt`): every other field and element kept (colours, intensities, faces, LAS "
    "records and VLRs, every other column and line of a text file, an array's other columns, an NPZ's other "
    "arrays), normals rotated (an NPZ's `normals` array too), x, y, z in the file's precision "
    "(4-byte floats become 8-byte ones for map coordinates; LAS keeps its scale and, where the moved points fit, its "
    "offsets; text keeps the decimals of its coordinates); a PTX file keeps its rows and has each scan's header "
    "composed with the pose. An E57 source comes back as E57, named `<stem>_aligned.e57`: every scan's and image's "
    "pose composed with the transform, its points, images and every other field copied as they are. A file that "
    "cannot hold its moved points (a LAS span beyond its 32-bit integers at "
    "its scale) is a 422 naming why.",
    openapi_extra=_multipart(_ALIGNED_SCHEMA),
    responses={
        200: {
            "description": "The moved source (Content-Disposition names it): PLY, PCD, NPY and NPZ as "
            "application/octet-stream, LAS as application/vnd.las, LAZ as "
            "application/vnd.laszip, CSV as text/csv, XYZ, TXT, PTS and PTX as text/plain (UTF-8), E57 as model/e57.",
            "content": {media: _BINARY for media in dict.fromkeys(ALIGNED_MEDIA_TYPES.values())},
        },
        **error_docs(400, 401, 408, 413, 415, 422, 503, 504),
    },
)
async def register_aligned(request: Request) -> Response:
    settings, runner = get_settings(request), get_runner(request)
    bodies.require_media_type(request, bodies.MULTIPART)
    # a 2,000,000-point file decoded and moved: a slot as a registration's and a place among the aligned answers, both
    # held until the moved file (in /tmp until then) has been sent, so at most MFGNET_MAX_CONCURRENCY moved files
    # are on disk and a client that reads nothing holds them for MFGNET_BODY_TIMEOUT_S only
    release_answer = runner.limiter.admit_answer()
    try:
        slot = runner.admit()
    except BaseException:
        release_answer()
        raise
    try:
        form = await bodies.read_register_form(request, ("source",))  # the file stays spooled until decoded
        await bodies.refuse_oversized_uploads(form, settings.max_file_points)
        try:
            R, t = _aligned_transform(form.fields)
            upload = form.files["source"]

            def decode() -> np.ndarray:
                return bodies.decode_upload(upload, settings.max_file_points)  # [N, 3] float64, the shared reader

            def work(source: np.ndarray) -> tuple[BinaryIO, str]:
                aligned = source @ R.T + t  # [N, 3] float64
                if not np.isfinite(aligned).all():
                    raise APIError(422, "invalid request: the moved source leaves the float64 range")
                kind = source_format(upload.file)  # every format the reader decodes is one of KEPT_FORMATS
                if kind not in KEPT_FORMATS:  # the spooled file could not be read again
                    raise APIError(422, f"invalid request: {upload.label} could not be read again to be written moved")
                suffix = own_suffix(upload.file, kind, upload.filename)
                return moved_upload(upload, suffix, R, t, float(np.abs(aligned).max(initial=0.0))), suffix

            (content, suffix), _ = await runner.run(slot, work, request, decode)
        finally:
            form.close()
    except BaseException:
        slot.release()
        release_answer()
        raise
    stem = PurePath(upload.filename).stem or "source"
    headers = {"Content-Disposition": attachment(f"{_safe(stem)}_aligned{suffix}")}
    size = content.seek(0, 2)
    content.seek(0)
    return MovedFileResponse(
        content, (slot.release, release_answer), settings.body_timeout_s, media_type=ALIGNED_MEDIA_TYPES[suffix],
        headers={**headers, "Content-Length": str(size)},
    )


class MovedFileResponse(StreamingResponse):
    """The moved file streamed; the file is closed and ``releases`` called (the request's slot and aligned place) when
    the answer ends however it ends, and a client that reads none of it for ``stall_s`` (MFGNET_BODY_TIMEOUT_S) is
    dropped, as a stalled upload is."""

    def __init__(self, file: BinaryIO, releases: tuple[Callable[[], None], ...], stall_s: float, **kwargs: Any):
        size = file.seek(0, 2)
        file.seek(0)
        super().__init__(streamed(file, size), **kwargs)
        self._file, self._releases, self._stall_s = file, releases, stall_s

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        async def send_within(message: Any) -> None:
            async with asyncio.timeout(self._stall_s):
                await send(message)

        try:
            await super().__call__(scope, receive, send_within)
        except TimeoutError:
            # dropped: closed now, what is still buffered for it discarded (transport.close() would keep the
            # connection, its buffers and its place under MFGNET_MAX_CONNECTIONS until the client reads them)
            state = scope.setdefault("state", {})
            state[DROPPED_CLIENT] = True
            abort = state.get(ABORT_CONNECTION)
            if abort is not None:
                abort()
                await asyncio.sleep(0)  # connection_lost runs: uvicorn sees a disconnect, not an unfinished answer
            raise ClientDisconnect from None
        finally:
            self._file.close()
            for release in self._releases:
                release()


def moved_upload(upload: bodies.Upload, suffix: str, R: np.ndarray, t: np.ndarray, largest: float) -> BinaryIO:
    """The spooled ``upload`` (a format of :data:`service.formats.moved.KEPT_FORMATS`) moved by ``R [3, 3]``,
    ``t [3]`` into a temporary file written as ``suffix`` (:func:`service.formats.moved.write_moved`), open for
    reading; its name is already removed, so the disk space is freed when it is closed, whatever becomes of the
    request. A 422 where the moved points do not fit the format (a LAS span beyond its 32-bit integers at its scale)
    or the upload cannot be written moved."""
    try:
        folder = tempfile.mkdtemp(prefix="mfgnet-aligned-")
    except OSError as exc:
        raise TempStorageError(exc, "the moved file") from None
    try:
        out = Path(folder) / f"aligned{suffix}"
        try:
            write_moved(upload.file, out, R, t, largest)
        except PointCloudFormatError as exc:
            raise APIError(422, f"invalid request: {upload.label} cannot be written moved: {exc}") from None
        except OSError as exc:  # writing it: the folder is full
            raise TempStorageError(exc, "the moved file") from None
        return open(out, "rb")  # closed by streamed()
    finally:
        shutil.rmtree(folder, ignore_errors=True)


async def streamed(file: BinaryIO, size: int) -> AsyncIterator[bytes]:
    """``file``'s ``size`` bytes, :data:`STREAM_CHUNK_BYTES` at a time read in a worker thread; closed at the end or
    when the response stops early (the client gone). No read after the last byte: the answer's end goes out at once
    after it, before a client that read its Content-Length and closed is seen to have gone (a 499 otherwise)."""
    left = size
    try:
        while left > 0 and (chunk := await run_in_threadpool(file.read, min(STREAM_CHUNK_BYTES, left))):
            left -= len(chunk)
            yield chunk
    finally:
        file.close()


def attachment(name: str) -> str:
    """A ``Content-Disposition`` naming the download ``name``: ``filename`` in ASCII (other characters as ``_``: HTTP
    headers are Latin-1, and a Cyrillic or CJK name was a 500), and where that differs the name itself as RFC 6266's
    ``filename*`` (UTF-8, percent-encoded), which browsers prefer."""
    ascii_name = "".join(c if c.isascii() else "_" for c in name)
    if ascii_name == name:
        return f'attachment; filename="{name}"'
    return f"attachment; filename=\"{ascii_name}\"; filename*=UTF-8''{quote(name, safe='')}"


def _aligned_transform(fields: dict[str, str]) -> tuple[np.ndarray, np.ndarray]:
    """The form's ``transform`` field as a rigid ``(R [3, 3], t [3])``, or a 422 naming what is wrong (another field
    too: ``/v1/register``'s options do nothing here, and a caller who sends them should hear so, as there)."""
    for name in fields:
        if name != "transform":
            raise APIError(422, f"invalid request: {name[:64]}: Extra inputs are not permitted (this route takes the "
                                "file source and the field transform)")
    if "transform" not in fields:
        raise APIError(422, "invalid request: transform: missing (a JSON 4x4 array)")
    matrix = _json_field(fields["transform"], "transform")
    if not _numbers_only(matrix):  # numpy would read "1" and true as numbers; /v1/register's schema does not
        raise APIError(422, "invalid request: transform: expected a JSON 4x4 array of numbers")
    try:
        return check_transform(matrix)
    except InputError as exc:
        raise APIError(422, f"invalid request: transform: {str(exc).removeprefix('initial_transform ')}") from None
    except (ValueError, TypeError, OverflowError):  # not a numeric array
        raise APIError(422, "invalid request: transform: expected a JSON 4x4 array of numbers") from None


def _numbers_only(matrix: Any) -> bool:
    """Whether ``matrix`` is a JSON list of lists of numbers (``true`` and ``"1"`` are none)."""
    rows = matrix if isinstance(matrix, list) and all(isinstance(row, list) for row in matrix) else [matrix]
    return all(
        isinstance(row, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in row)
        for row in rows
    )


def _safe(stem: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in stem)[:80]


def install(app: FastAPI) -> None:
    """``GET /`` and the page's scripts and styles under ``/page/``."""
    app.include_router(page_router)
    app.mount("/page", StaticFiles(directory=WEB_DIR), name="page")
