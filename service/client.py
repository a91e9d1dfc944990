"""A small HTTP client for the MFGNet service (``mfgnet serve``).

    >>> with MfgnetClient("http://127.0.0.1:8000") as client:
    ...     client.wait_ready(timeout=30)
    ...     response = client.register(source, target, refine="icp")
    ...     R, t = pose_from_response(response)  # target ~= source @ R.T + t

Every server error (``{"error": "..."}`` with a 4xx/5xx status), and a server that cannot be
reached, raises :class:`MfgnetError` carrying the status (0 when no response came) and the
server's message. Clouds may be any array-like of numbers (arrays of any numeric dtype, nested lists,
lists of numpy rows) and options numpy scalars; what the server refuses (a wrong shape, NaN or
infinite coordinates) is its 422, not a local error. A cloud with NaN or infinite values is sent as an
``.npy`` file even without ``binary=True``, because JSON has no such numbers and the server's reader of
files names how many rows hold them and the first.

A 503 with ``Retry-After`` (the server busy: every slot taken and its queue full; or the model still loading) is
sent again after the wait it asks for, ``busy_retries`` times at most (2 by default; registration is a pure
function of the request, so sending it again is safe). A 503 without ``Retry-After`` (a model that failed to load),
any 4xx and a timeout are raised at once.
"""

from __future__ import annotations

import io
import json
import math
import os
import random
import time
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime
from pathlib import Path
from typing import Any, Literal

import httpx
import numpy as np
from numpy.typing import ArrayLike

from service.normalization import rms_radius

REGISTER_PATH = "/v1/register"
MODELS_PATH = "/v1/models"
READY_PATH = "/v2/health/ready"
# Above this magnitude (caller's units) float32 rounds coordinates by more than ~1/1000 of a unit, so binary
# uploads of arrays are sent recentred by a shared offset and the pose is mapped back (shared_offset).
LARGE_COORDINATE = 1.0e4
# ... or where float32's step at a cloud's largest coordinate reaches this share of its RMS radius: a small object far
# from the origin (the server's float32 check warns at 0.001 of the radius; service/stages/float32_check.py)
FLOAT32_STEP_SHARE = 1.0e-4
BUSY_RETRIES = 2  # MfgnetClient's default: see its docstring
MAX_RETRY_WAIT_S = 10.0  # the longest wait before a retry, whatever Retry-After asks
RETRY_JITTER = 0.2  # each wait is Retry-After x U(1, 1.2), so clients refused together do not all return together


class MfgnetError(Exception):
    """The server answered with an error status (or could not be reached: ``status == 0``).

    ``retry_after``: the seconds a 503's ``Retry-After`` asked for (the server busy or loading) when the client gave
    up on it (``busy_retries`` spent, or a wait past ``timeout``); ``None`` for every other error.
    ``request_id``: the answer's ``X-Request-ID``, which the server's access line and logs carry (``None`` without
    an answer)."""

    def __init__(self, status: int, message: str, retry_after: float | None = None, request_id: str | None = None):
        super().__init__(f"HTTP {status}: {message}" if status else message)
        self.status = status
        self.message = message
        self.retry_after = retry_after
        self.request_id = request_id


class MfgnetClient:
    """``MfgnetClient(base_url, api_key=None, timeout=30.0, busy_retries=2)``; usable as a context manager.

    ``api_key`` is sent as ``Authorization: Bearer <key>`` (the server asks for it when it sets
    ``MFGNET_API_KEY``).
    ``timeout``: seconds httpx waits for each step of one try (connecting, sending, the answer). It also bounds a
    call's retries: a retry is sent only if its wait ends within ``timeout`` seconds of the call's start, and httpx
    then waits for it only as long as is left of those seconds (so a 503 is raised at once where its wait, below,
    would end past ``timeout``).
    ``busy_retries``: how many times a call sends its request again after a 503 with ``Retry-After`` (the server
    busy, ``MFGNET_MAX_CONCURRENCY`` registrations running and ``MFGNET_MAX_QUEUE`` waiting; or its model still
    loading), each after the header's seconds (at most ``MAX_RETRY_WAIT_S``, 10, plus up to 20% random jitter).
    ``0`` raises the first 503 at once, as ``MfgnetError`` with ``retry_after`` set, for a caller with its own
    policy. The default, 2, rides out a burst: the server asks for 1 s when busy and 2 s while loading, so it adds
    at most about 2.4 s (busy) or 4.8 s (loading) to a call, and at most triples what one client sends to a
    server that stays overloaded, which is then reported within seconds instead of hidden. A 503 without
    ``Retry-After`` (a model that failed to load), every 4xx and a timeout are never retried.
    ``transport``: an ``httpx`` transport for what the defaults do not cover, e.g.
    ``httpx.HTTPTransport(retries=3)`` to retry failed connections while a server restarts, a Unix socket
    (``uds=``), a local address or TLS settings. It replaces httpx's default, so ``HTTP(S)_PROXY`` variables
    are then not read (pass ``proxy=`` to the transport instead).
    """

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 30.0,
                 transport: httpx.BaseTransport | None = None, busy_retries: int = BUSY_RETRIES):
        headers = {"Accept": "application/json"}
        if api_key:
            if not (api_key.isascii() and api_key.isprintable()) or api_key != api_key.strip():
                raise ValueError("api_key must be printable ASCII without spaces or line breaks around it (a key read "
                                 "from a file keeps its line break: strip it)")
            headers["Authorization"] = f"Bearer {api_key}"
        busy_retries = _plain(busy_retries)
        if isinstance(busy_retries, bool) or not isinstance(busy_retries, int) or busy_retries < 0:
            raise ValueError(f"busy_retries must be an integer >= 0, got {busy_retries!r}")
        self.base_url = base_url.rstrip("/")
        self.busy_retries = busy_retries
        timeout = _plain(timeout)
        self._budget_s = float(timeout) if isinstance(timeout, (int, float)) else None  # None: no timeout to keep
        try:
            self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout, transport=transport)
        except httpx.InvalidURL as exc:
            raise ValueError(f"base_url {base_url!r} is not a URL ({exc})") from None

    # -- lifecycle ---------------------------------------------------------------------------
    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> MfgnetClient:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- endpoints ---------------------------------------------------------------------------
    def register(
        self,
        source: ArrayLike | str | os.PathLike[str],
        target: ArrayLike | str | os.PathLike[str],
        model: str | None = None,
        iterations: int | None = None,
        keypoints: int | None = None,
        refine: str | None = None,
        initial_transform: ArrayLike | None = None,
        return_correspondences: bool = True,
        return_iterations: bool = False,
        binary: bool = False,
        rotation_search: bool | Literal["auto"] | None = None,
        refine_points: int | None = None,
        drop_isolated: bool | None = None,
    ) -> dict:
        """``POST /v1/register``: the pose ``source -> target`` as the server's JSON dict.

        Args:
            source: ``(N, 3)`` points (any array-like of numbers), or the path of a point-cloud file (PLY, PCD,
                LAS/LAZ, NPY/NPZ, XYZ/CSV/TXT), uploaded as it is and read by the server's reader (the CLI's):
                LAS/UTM coordinates keep their float64 precision, and the pose is in the file's frame.
            target: ``(M, 3)`` points, or a file path.
            model, iterations, keypoints, refine (``"none"`` | ``"icp"`` | ``"icp-plane"`` |
                ``"icp-plane-multistart"``), initial_transform (4x4): left out of the request when ``None``
                (the server's defaults apply).
            rotation_search: ``True`` = search over initial rotations covering SO(3) (any relative
                orientation, much slower); ``"auto"`` = only when the plain result looks wrong (the
                response's ``timing_ms`` then has a ``search`` key); ``False`` = never; ``None`` (default) =
                the server's (``MFGNET_DEFAULT_ROTATION_SEARCH``: ``auto`` unless the operator set it, and
                never a search with ``refine="none"``).
            refine_points: points per cloud the refinement uses (``None``: the network's working clouds).
            drop_isolated: ``False`` keeps isolated points as sampling candidates (``None``: the server's, true).
            binary: send the clouds as multipart ``.npy`` float32 files ``source`` / ``target`` with
                the options as form fields (smaller and faster than JSON for large clouds). Coordinates
                float32 rounds coarsely (beyond ``LARGE_COORDINATE``, e.g. UTM, or a small object far from the
                origin) are first moved near the origin (:func:`cloud_offsets`: one
                offset for both where that serves, else each cloud its own), and the returned pose is moved back: it
                is in the caller's frame. Where the clouds need offsets of their own and an ``initial_transform`` is
                given, they go as float64 ``.npy`` unmoved instead, so that the server can still tell a prior given
                target-to-source. An array beside a file path goes as float64 too.
                Without ``binary``, a cloud with NaN or infinite values is sent as a float64 ``.npy`` file, for the
                server's 422 to name its rows.

        Raises:
            MfgnetError: the server refused the request or could not be reached.
            OSError: a path that cannot be read.
            ValueError: ``binary=True`` with a cloud that numpy cannot read as numbers.
        """
        options: dict[str, Any] = {
            "model": model,
            "iterations": iterations,
            "keypoints": keypoints,
            "refine": refine,
            "initial_transform": None if initial_transform is None else _as_list(_as_array(initial_transform)),
            "return_correspondences": return_correspondences,
            "return_iterations": return_iterations,
            "rotation_search": rotation_search,
            "refine_points": refine_points,
            "drop_isolated": drop_isolated,
        }
        options = {key: _plain(value) for key, value in options.items() if value is not None}
        source, target = (cloud if _is_path(cloud) else _as_array(cloud) for cloud in (source, target))
        paths = _is_path(source) or _is_path(target)
        arrays = isinstance(source, np.ndarray) and isinstance(target, np.ndarray)
        if binary or paths or (arrays and (_non_finite(source) or _non_finite(target))):
            offsets = None if paths or not binary else cloud_offsets(source, target)
            exact = False  # float64 .npy: nothing rounded, nothing moved
            if offsets is not None and "initial_transform" in options and not np.array_equal(*offsets):
                # each cloud moved by its own offset conjugates the prior differently on each side: the server could no
                # longer see a prior given target-to-source as the result's inverse (its T_source_target hint)
                offsets, exact = None, True
            if offsets is not None:  # float32 would round these coordinates: send each cloud recentred
                source, target = _recentred(source, offsets[0]), _recentred(target, offsets[1])
                if "initial_transform" in options:
                    options["initial_transform"] = recentred_transform(options["initial_transform"], *offsets)
            # an array beside a path is sent as given (float64): it is neither recentred nor would float32 hold a
            # map's coordinates; non-finite clouds too
            dtype = np.float32 if binary and not paths and not exact else np.float64
            files = {name: _upload(name, cloud, dtype) for name, cloud in (("source", source), ("target", target))}
            form = {key: _form_value(value) for key, value in options.items()}
            response = self._request("POST", REGISTER_PATH, data=form, files=files)
            return response if offsets is None else pose_in_caller_frame(response, *offsets)
        body = {"source": _as_list(source), "target": _as_list(target), **options}
        content = json.dumps(body, separators=(",", ":"), default=_json_default)  # NaN literals: the server's 422
        return self._request("POST", REGISTER_PATH, content=content, headers={"Content-Type": "application/json"})

    def models(self) -> list:
        """``GET /v1/models``: the served models (a list of dicts)."""
        payload = self._request("GET", MODELS_PATH)
        if isinstance(payload, dict) and "models" in payload:
            return list(payload["models"])
        return list(payload)

    def ready(self) -> bool:
        """``GET /v2/health/ready`` answers 200 (False on any other status or no answer)."""
        try:
            return self._http.get(READY_PATH).status_code == 200
        except httpx.HTTPError:
            return False

    def wait_ready(self, timeout: float = 60.0, interval: float = 0.2) -> None:
        """Poll :meth:`ready` until it is true; ``TimeoutError`` after ``timeout`` seconds."""
        timeout, interval = float(timeout), float(interval)  # time.sleep takes no numpy float32
        deadline = time.monotonic() + timeout
        while not self.ready():
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{self.base_url} was not ready within {timeout:g} s")
            time.sleep(interval)

    # -- plumbing ----------------------------------------------------------------------------
    def _request(self, method: str, path: str, **kwargs) -> Any:
        """The JSON answer to a request, sent again after a 503 with ``Retry-After`` (see the class). ``kwargs`` hold
        the whole body as bytes or text (file uploads are read whole by ``_upload``), so each try sends all of it."""
        started = time.monotonic()
        retries = 0
        while True:
            response = self._send(method, path, retries, **kwargs)
            if response.status_code < 400:
                break
            retry_after = _retry_after(response) if response.status_code == 503 else None
            request_id = response.headers.get("x-request-id")
            if retry_after is None:
                raise MfgnetError(response.status_code, _error_message(response), request_id=request_id)
            wait_s = min(retry_after, MAX_RETRY_WAIT_S) * random.uniform(1.0, 1.0 + RETRY_JITTER)
            left_s = None if self._budget_s is None else self._budget_s - (time.monotonic() - started) - wait_s
            if retries >= self.busy_retries or (left_s is not None and left_s <= 0):
                why = (f"busy_retries={self.busy_retries}" if retries >= self.busy_retries
                       else f"a wait of {wait_s:.1f} s would end past the {self._budget_s:g} s timeout")
                done = f"given up after {retries} retr{'y' if retries == 1 else 'ies'}" if retries else "not retried"
                header = response.headers["Retry-After"]
                raise MfgnetError(503, f"{_error_message(response)} (Retry-After: {header}; {done}: {why})",
                                  retry_after=retry_after, request_id=request_id)
            time.sleep(wait_s)
            retries += 1
            if left_s is not None:
                kwargs["timeout"] = left_s  # a retry gets what is left of the call's timeout
        try:
            return response.json()
        except ValueError as exc:
            text = response.text[:200]
            raise MfgnetError(response.status_code, f"the server's answer is not JSON: {text!r}",
                              request_id=response.headers.get("x-request-id")) from exc

    def _send(self, method: str, path: str, retries: int, **kwargs) -> httpx.Response:
        """One try; no answer raises ``MfgnetError`` with status 0 (never retried: the request may be running)."""
        after = f" on retry {retries} after a 503 with Retry-After" if retries else ""
        try:
            return self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as exc:
            raise MfgnetError(0, f"no answer from {self.base_url}{path} in time{after} ({exc})") from exc
        except httpx.HTTPError as exc:
            raise MfgnetError(0, f"cannot reach {self.base_url}{path}{after} ({exc})") from exc


def pose_from_response(response: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` of a register response (``target ~= source @ R.T + t``).

    Uses ``transform`` (4x4) when present, else ``rotation`` and ``translation``.

    Raises:
        ValueError: the response has no pose of the right shape.
    """
    if "transform" in response:
        T = np.asarray(response["transform"], dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"transform must be 4x4, got shape {T.shape}")
        return T[:3, :3].copy(), T[:3, 3].copy()
    if "rotation" not in response or "translation" not in response:
        raise ValueError("the response has neither 'transform' nor 'rotation' and 'translation'")
    R = np.asarray(response["rotation"], dtype=np.float64)
    t = np.asarray(response["translation"], dtype=np.float64)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"rotation must be 3x3 and translation length 3, got {R.shape} and {t.shape}")
    return R, t


def cloud_offsets(source: ArrayLike, target: ArrayLike) -> tuple[np.ndarray, np.ndarray] | None:
    """``None`` when float32 rounds neither cloud coarsely (:func:`rounds_coarsely`), else the offsets ``[3]``, ``[3]``
    that the source and the target are moved by before float32: one for both (the source's centroid, rounded to whole
    units), so that the server sees the clouds as the caller placed them, where float32 then rounds neither coarsely;
    else each cloud's own centroid where float32 rounds it coarsely and zero where not (a local scan beside a map in UTM
    keeps its coordinates, and the map comes near the origin too; a small object far from the origin counts as far). A
    far cloud whose coordinates are float32 values already is not moved (offset zero, and no shared offset): it loses
    nothing to float32, and the server sees it as it is.

    Only the rows the server can take count (``x, y, z`` finite and within float32's range): a NaN row
    stays the one row the server names instead of turning the offset, and so every row, into NaN. Clouds
    that are not ``(N, >=3)`` numbers get ``None``: they are sent as they are, for the server to name them."""
    if any(np.asarray(cloud).dtype.kind not in "iuf" for cloud in (source, target)):  # booleans, complex numbers
        return None
    src, tgt = (_usable_rows(np.asarray(cloud, np.float64)) for cloud in (source, target))  # [N', 3], [M', 3]
    if src is None or tgt is None:
        return None
    far = [rounds_coarsely(rows) for rows in (src, tgt)]
    if not any(far):
        return None
    # float32 values already (a float32 file or array): nothing rounds them, so they are sent as they are and the
    # server sees what the caller has (its float32 rounding warning, the pose an in-process run gives)
    exact = [is_far and np.array_equal(rows, rows.astype(np.float32))
             for rows, is_far in zip((src, tgt), far, strict=True)]
    if all(is_exact or not is_far for is_exact, is_far in zip(exact, far, strict=True)):
        return None
    if not any(exact):
        shared = np.round((src if len(src) else tgt).mean(0))
        # one offset only where it leaves neither cloud rounded coarsely: a small object near the origin moved by a
        # far cloud's centroid (or left beside it where that centroid rounds to zero) would lose what it had
        if not rounds_coarsely(src - shared) and not rounds_coarsely(tgt - shared):
            return shared, shared
    own = tuple(np.round(rows.mean(0)) if is_far and not is_exact else np.zeros(3)
                for rows, is_far, is_exact in zip((src, tgt), far, exact, strict=True))
    return own[0], own[1]


def rounds_coarsely(rows: np.ndarray) -> bool:
    """Whether float32 would round the cloud ``rows [N, 3]`` coarsely: a coordinate beyond ``LARGE_COORDINATE``, or
    float32's step at its largest coordinate at least ``FLOAT32_STEP_SHARE`` of its RMS radius."""
    if not len(rows):
        return False
    largest = float(np.abs(rows).max())
    if largest > LARGE_COORDINATE:
        return True
    return float(np.spacing(np.float32(largest))) >= FLOAT32_STEP_SHARE * rms_radius(rows)


def recentred_transform(transform: ArrayLike, source_offset: np.ndarray, target_offset: np.ndarray) -> list:
    """A caller-frame ``src_to_tgt`` 4x4 as the same motion between the source moved by ``-source_offset`` and the
    target moved by ``-target_offset``: ``t' = t + R source_offset - target_offset``."""
    T = np.array(transform, dtype=np.float64)  # [4, 4]
    T[:3, 3] += T[:3, :3] @ source_offset - target_offset
    return T.tolist()


def pose_in_caller_frame(response: dict, source_offset: np.ndarray, target_offset: np.ndarray) -> dict:
    """A response for the source moved by ``-source_offset`` and the target by ``-target_offset``, with its poses
    (final and per iteration) moved back: ``t = t' + target_offset - R source_offset``; rotations and every other
    field are the same in both frames."""
    from service.pose_json import pose_fields

    R, t = pose_from_response(response)
    response.update(pose_fields(R, t + target_offset - R @ source_offset))
    for pose in response.get("iteration_poses") or []:
        R_i = np.asarray(pose["rotation"], np.float64)
        moved_back = np.asarray(pose["translation"], np.float64) + target_offset - R_i @ source_offset
        pose["translation"] = moved_back.tolist()
    return response


def _usable_rows(cloud: np.ndarray) -> np.ndarray | None:
    """The ``x, y, z`` ``[N', 3]`` of the rows of ``cloud [N, >=3]`` whose three coordinates are finite and
    within float32's range (the server refuses the others), or ``None`` if ``cloud`` is not ``(N, >=3)``."""
    if cloud.ndim != 2 or cloud.shape[1] < 3:
        return None
    xyz = cloud[:, :3]
    usable = (np.abs(xyz) <= np.finfo(np.float32).max).all(axis=1)  # [N]; NaN compares false
    return xyz if usable.all() else xyz[usable]


def _recentred(cloud: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """float64 ``cloud [N, >=3]`` with its ``x, y, z`` moved by ``-offset``; further columns as they are."""
    moved = np.array(cloud, dtype=np.float64)
    moved[:, :3] -= offset
    return moved


def _as_array(points: ArrayLike) -> ArrayLike:
    """``points`` as a numpy array if numpy reads it as numbers (any array-like, any numeric dtype), else as
    given (ragged rows, strings): the server then names the problem."""
    try:
        array = np.asarray(points)
    except ValueError:  # ragged rows
        return points
    return array if array.dtype.kind in "biuf" else points


def _non_finite(cloud: ArrayLike | str | os.PathLike[str]) -> bool:
    """A numeric array holding NaN or an infinity."""
    return isinstance(cloud, np.ndarray) and cloud.dtype.kind == "f" and not np.isfinite(cloud).all()


def _as_list(points: ArrayLike) -> list:
    return points.tolist() if isinstance(points, np.ndarray) else points


def _plain(value: Any) -> Any:
    """numpy scalars and arrays as plain Python (neither ``json`` nor the form fields take numpy types)."""
    return value.tolist() if isinstance(value, (np.ndarray, np.generic)) else value


def _json_default(value: Any) -> Any:
    """``json.dumps``'s ``default``: numpy values left inside lists (rows of a ragged cloud) as plain Python."""
    if isinstance(value, (np.ndarray, np.generic)):
        return _plain(value)
    if isinstance(value, complex):  # not a coordinate: sent as text, which the server names
        return str(value)
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


def _is_path(cloud: ArrayLike | str | os.PathLike[str]) -> bool:
    return isinstance(cloud, (str, os.PathLike))


def _upload(name: str, cloud: ArrayLike | str | os.PathLike[str],
            dtype: type[np.floating] = np.float32) -> tuple[str, bytes, str]:
    """A multipart file: a path's bytes under its own name, else the points as ``.npy`` of ``dtype``. Read whole
    once, so that every try of the request (``busy_retries``) sends all of it."""
    if _is_path(cloud):
        path = Path(cloud)
        return path.name, path.read_bytes(), "application/octet-stream"
    return f"{name}.npy", _npy_bytes(cloud, dtype), "application/octet-stream"


def _npy_bytes(points: ArrayLike, dtype: type[np.floating] = np.float32) -> bytes:
    """``points`` as ``.npy`` bytes of ``dtype`` where they are numbers; others (booleans, complex numbers, strings)
    unconverted, so that the server names their type rather than registering what a cast made of them."""
    array = np.asarray(points)
    buffer = io.BytesIO()
    with np.errstate(over="ignore"):  # beyond float32's range: inf, which the server names as such
        np.save(buffer, array.astype(dtype) if array.dtype.kind in "iuf" else array, allow_pickle=False)
    return buffer.getvalue()


def _form_value(value: bool | int | str | list | dict) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return str(value)


def _retry_after(response: httpx.Response) -> float | None:
    """The seconds a response's ``Retry-After`` asks to wait (delay-seconds or an HTTP-date; 0 for a date past), or
    ``None`` when it has none that can be read."""
    value = response.headers.get("Retry-After")
    if value is None:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = parsedate_to_datetime(value)
        except (TypeError, ValueError, IndexError):
            return None
        if when.tzinfo is None:  # an HTTP-date is GMT
            when = when.replace(tzinfo=UTC)
        seconds = (when - datetime.now(UTC)).total_seconds()
    return max(seconds, 0.0) if math.isfinite(seconds) else None


def _error_message(response: httpx.Response) -> str:
    """The server's ``error`` text (FastAPI's ``detail`` as a fallback, else the raw body)."""
    try:
        payload = response.json()
    except ValueError:
        return response.text.strip()[:500] or response.reason_phrase
    if isinstance(payload, dict):
        for key in ("error", "detail", "message"):
            if key in payload:
                value = payload[key]
                return value if isinstance(value, str) else json.dumps(value)
    return json.dumps(payload)[:500]
