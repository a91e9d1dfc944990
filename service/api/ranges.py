"""A ``Range`` header the static files cannot serve is ignored, as RFC 9110 14.2 asks, rather than refused.

Starlette's file responses (the page at ``/``, its files under ``/page``) answered a range of a unit other than
``bytes`` (``items=0-1``) or a malformed byte range (``bytes=5-1``) with a plain-text 400, where a server MUST ignore a
unit it does not understand and MAY ignore the rest. Such a header is taken off the request here: the whole file is
sent, 200. A well-formed range past the file's end keeps Starlette's 416.
"""

from __future__ import annotations

import re

from starlette.types import ASGIApp, Receive, Scope, Send

# bytes=<first>-[<last>] or bytes=-<suffix length>, comma-separated
_RANGE_SPEC = re.compile(r"\s*(?:(\d+)-(\d*)|-(\d+))\s*")


def servable(value: bytes) -> bool:
    """Whether ``value`` (a ``Range`` header) is a well-formed byte range set: each range ``first-[last]`` with
    ``first <= last``, or a non-empty suffix ``-length``."""
    unit, _, ranges = value.decode("latin-1").partition("=")
    if unit.strip().lower() != "bytes" or not ranges:
        return False
    for spec in ranges.split(","):
        match = _RANGE_SPEC.fullmatch(spec)
        if match is None:
            return False
        first, last, suffix = match.groups()
        if suffix is not None and int(suffix) == 0:
            return False
        if first is not None and last and int(last) < int(first):
            return False
    return True


class IgnoreUnservableRanges:
    """Takes a ``Range`` header that is not a well-formed byte range set off GET and HEAD requests."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] in ("GET", "HEAD"):
            headers = scope.get("headers", [])
            if any(key == b"range" and not servable(value) for key, value in headers):
                scope = {**scope, "headers": [(key, value) for key, value in headers if key != b"range"]}
        await self.app(scope, receive, send)
