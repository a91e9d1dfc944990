"""A small HTTP client for the MFGNet service (``mfgnet serve``).

    >>> with MfgnetClient("http://127.0.0.1:8000") as client:
    ...     client.wait_ready(timeout=30)
    ...     response = client.register(source, target, refine="icp")
    ...     R, t = pose_from_response(response)  # target ~= source @ R.T + t

Every server error (``{"error": "..."}`` with a 4xx/5xx status), and a server that cannot be
reached, raises :class:`MfgnetError` carrying the status (0 when no response came) and the
server's message.
"""

from __future__ import annotations

import io
import json
import os
import time
from pathlib import Path
from typing import Any, Literal

import httpx
import numpy as np
from numpy.typing import ArrayLike

REGISTER_PATH = "/v1/register"
MODELS_PATH = "/v1/models"
READY_PATH = "/v2/health/ready"
# Above this magnitude (caller's units) float32 rounds coordinates by more than ~1/1000 of a unit, so binary
# uploads of arrays are sent recentred by a shared offset and the pose is mapped back (shared_offset).
LARGE_COORDINATE = 1.0e4


class MfgnetError(Exception):
    """The server answered with an error status (or could not be reached: ``status == 0``)."""

    def __init__(self, status: int, message: str):
        super().__init__(f"HTTP {status}: {message}" if status else message)
        self.status = status
        self.message = message


class MfgnetClient:
    """``MfgnetClient(base_url, api_key=None, timeout=30.0)``; usable as a context manager.

    ``api_key`` is sent as ``Authorization: Bearer <key>`` (the server asks for it when it sets
    ``MFGNET_API_KEY``).
    ``transport`` (an ``httpx`` transport) is for tests.
    """

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 30.0,
                 transport: httpx.BaseTransport | None = None):
        headers = {"Accept": "application/json"}
        if api_key:
            headers["Authorization"] = f"Bearer {api_key}"
        self.base_url = base_url.rstrip("/")
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout, transport=transport)

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
            source: ``(N, 3)`` points (array or nested lists), or the path of a point-cloud file (PLY, PCD,
                LAS/LAZ, NPY/NPZ, XYZ/CSV/TXT), uploaded as it is and read by the server's reader (the CLI's):
                LAS/UTM coordinates keep their float64 precision, and the pose is in the file's frame.
            target: ``(M, 3)`` points, or a file path.
            model, iterations, keypoints, refine (``"none"`` | ``"icp"`` | ``"icp-plane"`` |
                ``"icp-plane-multistart"``), initial_transform (4x4): left out of the request when ``None``
                (the server's defaults apply).
            rotation_search: ``True`` = search over initial rotations covering SO(3) (any relative
                orientation, much slower); ``"auto"`` = only when the plain result looks wrong (the
                response's ``timing_ms`` then has a ``search`` key); ``False`` = never; ``None`` (default) =
                the server's (``MFGNET_DEFAULT_ROTATION_SEARCH``, off unless the operator set it).
            refine_points: points per cloud the refinement uses (``None``: the network's working clouds).
            drop_isolated: ``False`` keeps isolated points as sampling candidates (``None``: the server's, true).
            binary: send the clouds as multipart ``.npy`` float32 files ``source`` / ``target`` with
                the options as form fields (smaller and faster than JSON for large clouds). Coordinates
                beyond ``LARGE_COORDINATE`` (e.g. UTM) are first moved by one shared offset
                (:func:`shared_offset`), and the returned pose is moved back: it is in the caller's frame.

        Raises:
            MfgnetError: the server refused the request or could not be reached.
        """
        options: dict[str, Any] = {
            "model": model,
            "iterations": iterations,
            "keypoints": keypoints,
            "refine": refine,
            "initial_transform": None if initial_transform is None else np.asarray(initial_transform).tolist(),
            "return_correspondences": return_correspondences,
            "return_iterations": return_iterations,
            "rotation_search": rotation_search,
            "refine_points": refine_points,
            "drop_isolated": drop_isolated,
        }
        options = {key: value for key, value in options.items() if value is not None}
        if binary or _is_path(source) or _is_path(target):
            offset = None if _is_path(source) or _is_path(target) else shared_offset(source, target)
            if offset is not None:  # float32 would round these coordinates: send both clouds recentred
                source, target = np.asarray(source, np.float64) - offset, np.asarray(target, np.float64) - offset
                if "initial_transform" in options:
                    options["initial_transform"] = recentred_transform(options["initial_transform"], offset)
            files = {name: _upload(name, cloud) for name, cloud in (("source", source), ("target", target))}
            form = {key: _form_value(value) for key, value in options.items()}
            response = self._request("POST", REGISTER_PATH, data=form, files=files)
            return response if offset is None else pose_in_caller_frame(response, offset)
        body = {"source": _as_list(source), "target": _as_list(target), **options}
        return self._request("POST", REGISTER_PATH, json=body)

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
        deadline = time.monotonic() + timeout
        while not self.ready():
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{self.base_url} was not ready within {timeout:g} s")
            time.sleep(interval)

    # -- plumbing ----------------------------------------------------------------------------
    def _request(self, method: str, path: str, **kwargs) -> Any:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as exc:
            raise MfgnetError(0, f"no answer from {self.base_url}{path} in time ({exc})") from exc
        except httpx.HTTPError as exc:
            raise MfgnetError(0, f"cannot reach {self.base_url}{path} ({exc})") from exc
        if response.status_code >= 400:
            raise MfgnetError(response.status_code, _error_message(response))
        try:
            return response.json()
        except ValueError as exc:
            text = response.text[:200]
            raise MfgnetError(response.status_code, f"the server's answer is not JSON: {text!r}") from exc


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


def shared_offset(source: ArrayLike, target: ArrayLike) -> np.ndarray | None:
    """``None`` when every coordinate of both clouds is within ``LARGE_COORDINATE``, else one offset ``[3]``
    (the source's centroid, rounded to whole units) that both clouds are moved by before float32."""
    src, tgt = np.asarray(source, np.float64), np.asarray(target, np.float64)
    if max(np.abs(src).max(initial=0.0), np.abs(tgt).max(initial=0.0)) <= LARGE_COORDINATE:
        return None
    return np.round(src.reshape(-1, 3).mean(0))


def recentred_transform(transform: ArrayLike, offset: np.ndarray) -> list:
    """A caller-frame ``src_to_tgt`` 4x4 as the same motion between the clouds moved by ``-offset``."""
    T = np.array(transform, dtype=np.float64)  # [4, 4]
    T[:3, 3] += T[:3, :3] @ offset - offset
    return T.tolist()


def pose_in_caller_frame(response: dict, offset: np.ndarray) -> dict:
    """A response for clouds moved by ``-offset``, with its poses (final and per iteration) moved back:
    ``t = t' + offset - R offset``; rotations and every other field are the same in both frames."""
    from service.pose_json import pose_fields

    R, t = pose_from_response(response)
    response.update(pose_fields(R, t + offset - R @ offset))
    for pose in response.get("iteration_poses") or []:
        R_i = np.asarray(pose["rotation"], np.float64)
        pose["translation"] = (np.asarray(pose["translation"], np.float64) + offset - R_i @ offset).tolist()
    return response


def _as_list(points: ArrayLike) -> list:
    return np.asarray(points).tolist() if isinstance(points, np.ndarray) else points


def _is_path(cloud: ArrayLike | str | os.PathLike[str]) -> bool:
    return isinstance(cloud, (str, os.PathLike))


def _upload(name: str, cloud: ArrayLike | str | os.PathLike[str]) -> tuple[str, bytes, str]:
    """A multipart file: a path's bytes under its own name, else the points as float32 ``.npy``."""
    if _is_path(cloud):
        path = Path(cloud)
        return path.name, path.read_bytes(), "application/octet-stream"
    return f"{name}.npy", _npy_bytes(cloud), "application/octet-stream"


def _npy_bytes(points: ArrayLike) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(points, dtype=np.float32), allow_pickle=False)
    return buffer.getvalue()


def _form_value(value: bool | int | str | list | dict) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return str(value)


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
