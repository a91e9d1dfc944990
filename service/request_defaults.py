"""What the service runs for a request that leaves options out: one place for the HTTP API
(``service.api.runner``), ``mfgnet register`` and :class:`service.in_process.LocalRegistrar`, so that the three give
one answer for one request. ``Registrar.register`` itself keeps the paper's pipeline (``refine=None``, no search).

Standard library only, so that ``mfgnet --help`` and the settings can use it without loading the pipeline.
"""

from __future__ import annotations

from service.refine_modes import SERVICE_DEFAULT_REFINE
from service.search_mode import SERVICE_DEFAULT_ROTATION_SEARCH, service_rotation_search

# The model a request or `mfgnet register` runs when it names none (the server's MFGNET_DEFAULT_MODEL): trained for
# independently sampled scans; clean/noise/unseen reproduce the paper.
DEFAULT_MODEL = "general"

# What a request's network options may be (the model's own are defaults within them): the HTTP schema, the command
# line and the pipeline check these.
MAX_ITERATIONS = 8
KEYPOINT_RANGE = (16, 512)
# ONNX Runtime threads per graph a server, `mfgnet register --threads` or LocalRegistrar may ask for
THREAD_RANGE = (1, 64)


def request_defaults(
    refine: str | None = None,
    rotation_search: bool | str | None = None,
    *,
    default_refine: str = SERVICE_DEFAULT_REFINE,
    default_rotation_search: str = SERVICE_DEFAULT_ROTATION_SEARCH,
) -> tuple[str, bool | str]:
    """``(refine, rotation_search)`` for ``Registrar.register`` of a request that named ``refine`` and
    ``rotation_search`` (``None``: not named).

    ``refine``: the request's, else ``default_refine`` (the server's ``MFGNET_DEFAULT_REFINE``, ``"icp-plane"``).
    ``rotation_search``: the request's, else ``default_rotation_search`` (``"off"``, ``"on"`` or ``"auto"``; the
    server's ``MFGNET_DEFAULT_ROTATION_SEARCH``) for a refined request and ``False`` with ``refine="none"``.
    """
    refine = default_refine if refine is None else refine
    return refine, service_rotation_search(rotation_search, refine, default_rotation_search)
