"""Response bodies rendered with orjson.

The routes declare their pydantic ``response_model`` for the OpenAPI document, but return a
:class:`RenderedJSON` built from plain dicts: FastAPI then skips validating the body against the
model and serialising it twice (pydantic, then ``json.dumps``). The bodies are built from the
pipeline's arrays by ``runner.py`` with the model's field order and no ``None`` values, so the JSON
is the one ``response_model_exclude_none=True`` gave; floats keep every float64 bit (orjson writes
the shortest representation that reads back exactly, as ``json`` does). What the model's validation
used to guarantee (finite numbers, credibility in [0, 1], weights >= 0) ``runner.register_response``
checks on the arrays: a body breaking it is a 500, as before, never an invalid document.
"""

from __future__ import annotations

from typing import Any

import orjson
from starlette.responses import Response


def render_json(content: Any) -> bytes:
    """``content`` as compact JSON (numpy arrays and scalars included)."""
    return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY)


class RenderedJSON(Response):
    """``application/json`` response rendered with :func:`render_json` (bytes pass through)."""

    media_type = "application/json"

    def render(self, content: Any) -> bytes:
        return content if isinstance(content, bytes) else render_json(content)
