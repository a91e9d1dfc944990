"""Service settings from ``MFGNET_*`` environment variables (pydantic-settings).

Example::

    MFGNET_MODEL_DIRS=/models/a:/models/b MFGNET_API_KEY=s3cret MFGNET_PORT=9000 mfgnet serve
"""

from __future__ import annotations

import json
import re
from typing import Annotated, Literal
from urllib.parse import urlsplit

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from service.refine_modes import SERVICE_DEFAULT_REFINE
from service.request_defaults import DEFAULT_MODEL, THREAD_RANGE
from service.search_mode import SERVICE_DEFAULT_ROTATION_SEARCH

KiB = 1024
MiB = 1024 * KiB


def _split(value: object, separators: str) -> object:
    """``"a,b"`` -> ``["a", "b"]`` (a JSON list string or a list passes through)."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            return json.loads(text)
        return [part.strip() for part in re.split(separators, text) if part.strip()]
    return value

LOG_LEVELS = ("debug", "info", "warning", "error", "critical")  # the logging levels a setting may name


class Settings(BaseSettings):
    """Everything an operator can set; each field ``foo`` is read from ``MFGNET_FOO``."""

    model_config = SettingsConfigDict(env_prefix="MFGNET_", extra="ignore")

    model_dirs: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Extra model folders (a model folder, or a folder of model folders); comma or colon separated.",
    )
    bundled_models: bool = Field(True, description="Also serve the models shipped in service/models.")
    models: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Serve only these model names, comma separated (empty: every discovered model). Each "
        "model holds five ONNX Runtime sessions, so a one-model deployment uses far less memory.",
    )
    default_model: str = Field(
        DEFAULT_MODEL,
        description="Model used when a request names none (general: trained on independently sampled pairs).",
    )
    default_refine: Literal["none", "icp", "icp-plane", "icp-plane-multistart"] = Field(
        SERVICE_DEFAULT_REFINE,
        description="Refinement applied when a request names none: icp-plane (robust point-to-plane ICP, right for "
        "independently sampled scans); none = the network's pose alone (lowest latency, the paper's pipeline).",
    )
    default_rotation_search: Literal["off", "auto", "on"] = Field(
        SERVICE_DEFAULT_ROTATION_SEARCH,
        description="Rotation search for a request that names none, applied only when the request is refined: off "
        "(the lowest latency; clouds within ~45 deg of each other or with an initial_transform); auto = search "
        "when the plain result fits worse than the target's density allows, lies off a dense target's surface, or "
        "both clouds are rooms built of orthogonal planes (clouds at "
        "any relative orientation; the default. About 0.1-0.3 s more for the requests that search, which include "
        "partial views with little overlap); on = always.",
    )
    strict_readiness: bool = Field(
        True, description="Ready only if every discovered model loaded (Triton's --strict-readiness)."
    )
    host: str = "127.0.0.1"
    port: int = Field(8080, ge=0, le=65535)
    threads: int = Field(
        2, ge=THREAD_RANGE[0], le=THREAD_RANGE[1], description="ONNX Runtime intra-op threads per session."
    )
    max_points: int = Field(
        200_000, ge=32, description="Most points per cloud sent as JSON or OIP tensors; more is answered with 413."
    )
    max_file_points: int = Field(
        2_000_000,
        ge=32,
        description="Most points per cloud uploaded as a file (multipart, any "
        "format); more is answered with 413, known from the file's header before its points are "
        "read (text files: while reading). The server holds about 24 bytes per point per cloud while decoding.",
    )
    max_body_bytes: int = Field(
        64 * MiB,
        ge=1024,
        description="Largest body of a request that is not a multipart upload (JSON, OIP); more is answered with 413.",
    )
    max_buffered_bytes: int = Field(
        256 * MiB,
        ge=1024,
        description="Most bytes of JSON and OIP bodies held in memory at once, from their reading "
        "until their registration has decoded them (each counted at its Content-Length, else max_body_bytes); a "
        "request whose body does not fit waits, unread, for earlier ones (in arrival order), at most timeout_s: then "
        "503 with Retry-After and its slot is freed. Queued requests held "
        "their whole bodies: 18 of 64 MiB peaked above 1.1 GiB. A body larger than this is read alone.",
    )
    max_upload_bytes: int = Field(
        256 * MiB,
        ge=1024,
        description="Largest multipart upload body (both files and the options); more is "
        "answered with 413. The files are spooled to temporary files, not held in memory. 256 MiB holds two "
        "2,000,000-point clouds as float64 .npy (48 MB each) or as %.9g XYZ text (at most about 80 MB each).",
    )
    max_batch: int = Field(
        16,
        ge=1,
        description="Most pairs in one /v1/register/batch request; their clouds hold at "
        "most 2 x max_points points in all (as one pair may), so a batch's memory is a pair's.",
    )
    max_concurrency: int = Field(2, ge=1, description="Registrations running at once (worker threads).")
    max_queue: int = Field(16, ge=0, description="Registrations waiting for a worker; beyond that: 503.")
    timeout_s: float = Field(
        30.0,
        gt=0,
        allow_inf_nan=False,  # inf would turn the deadline off without a word
        description="Deadline per request after its body is read (and the longest wait for the body budget, "
        "max_buffered_bytes, before it: then 503), not counting the decoding of its clouds (a body over a size limit "
        "is a 413 whatever the deadline); then 504, and its registration stops at its next network call.",
    )
    body_timeout_s: float = Field(
        15.0,
        gt=0,
        allow_inf_nan=False,  # inf would turn the deadline off without a word
        description="Longest wait for the next piece of a request body; then 408 and the request's slot "
        "is freed (a request takes its slot before its body arrives, so stalled uploads would hold them all).",
    )
    body_min_rate: int = Field(
        32 * KiB,
        ge=1,
        description="Slowest accepted body upload, in bytes per second: a body must arrive within "
        "body_timeout_s plus one second per body_min_rate bytes received (Apache's mod_reqtimeout MinRate); then 408 "
        "and the slot is freed, so a client sending a byte now and then cannot hold a slot for hours.",
    )
    header_timeout_s: float = Field(
        15.0,
        gt=0,
        allow_inf_nan=False,  # inf would turn the deadline off without a word
        description="Longest time from a request's first byte to the end of its headers; then 408 and the "
        "connection is closed (slowloris: uvicorn alone waits for ever). A new connection that sends nothing is "
        "closed after keep_alive_s, as an idle one between requests is.",
    )
    max_connections: int = Field(
        1000,
        ge=1,
        description="Most connections open at once. A connection beyond it closes the one idle for "
        "longest (none sent yet, or kept alive between requests), else one answered before its body was read whole, "
        "else the one whose headers have been arriving for "
        "longest (408); when every open connection has a whole request "
        "it is refused at once with 503 and Retry-After. At start the open-file limit (nofile) is raised to its hard "
        "limit; where this cap, the listen backlog (2048) and 100 other file descriptors do not fit under it, the cap "
        "and the backlog are lowered to fit. An idle connection costs about 5 KiB.",
    )
    keep_alive_s: int = Field(
        75,
        ge=1,
        description="Idle keep-alive timeout; longer than clients' (httpx: 5 s) and load balancers' "
        "(often 60 s), so the server never closes a connection that a client is about to reuse.",
    )
    api_key: SecretStr | None = Field(None, description="If set, inference routes need 'Authorization: Bearer <key>'.")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Allowed CORS origins, comma separated; empty = CORS off."
    )
    log_level: str = Field("info", description="Log level: debug, info, warning, error or critical (any case).")

    @field_validator("log_level")
    @classmethod
    def _known_level(cls, value: str) -> str:
        if value.lower() not in LOG_LEVELS:
            raise ValueError(f"expected one of {', '.join(LOG_LEVELS)}")
        return value.lower()

    @field_validator("model_dirs", mode="before")
    @classmethod
    def _split_paths(cls, value: object) -> object:
        return _split(value, r"[,:]")

    @field_validator("models", "cors_origins", mode="before")
    @classmethod
    def _split_words(cls, value: object) -> object:
        return _split(value, r"[,\s]+")

    @field_validator("cors_origins")
    @classmethod
    def _origins(cls, values: list[str]) -> list[str]:
        """Each origin as browsers send it (``scheme://host[:port]``, lower case, no trailing ``/``), or ``*``."""
        return [_origin(value) for value in values]

    @field_validator("api_key", mode="before")
    @classmethod
    def _empty_key_is_none(cls, value: object) -> object:
        if isinstance(value, str) and not value.strip():
            return None
        if isinstance(value, str) and (value != value.strip() or not (value.isascii() and value.isprintable())):
            # no client can send it in 'Authorization: Bearer <key>': every request would be a 401 (MfgnetClient
            # refuses such a key too)
            raise ValueError("must be printable ASCII without spaces or line breaks around it (a key read from a "
                             "file often ends in a newline)")
        return value


def _origin(value: str) -> str:
    """``value`` as the ``Origin`` header browsers send: ``scheme://host[:port]`` in lower case, without a trailing
    ``/``; ``*`` as it is. A ValueError where it holds a path, a query or no host."""
    if value == "*":
        return value
    parts = urlsplit(value.strip())
    if parts.scheme.lower() not in ("http", "https") or not parts.netloc or parts.path not in ("", "/") \
            or parts.query or parts.fragment:
        raise ValueError("not an origin: expected scheme://host[:port] (e.g. https://app.example.com), without a path")
    return f"{parts.scheme.lower()}://{parts.netloc.lower()}"
