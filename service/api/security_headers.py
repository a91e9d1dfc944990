"""Browser-facing hardening headers on every response, the outermost layer (its 413s and last-resort 500 included).

``X-Content-Type-Options: nosniff``: a browser takes each body as its declared type (a JSON error that quotes the
request's path is never run as a script or rendered as HTML). ``Content-Security-Policy`` with ``frame-ancestors
'none'`` and ``X-Frame-Options: DENY`` (for browsers without CSP level 2): no other site frames the page or the API
pages to click through them (clickjacking). ``Referrer-Policy: no-referrer``: links out of the pages carry no URL.
A response that sets its own Content-Security-Policy (the page's, the API pages') keeps it; every other response,
JSON, PLY or a static file, gets :data:`NOTHING_ALLOWED`, which lets a browser load nothing on its behalf.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

FRAME_ANCESTORS = "frame-ancestors 'none'"  # every policy of this server ends with it
NOTHING_ALLOWED = f"default-src 'none'; {FRAME_ANCESTORS}"  # for responses that are not pages
HEADERS = (
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
)
CSP = b"content-security-policy"


def page_policy(directives: str) -> str:
    """A page's Content-Security-Policy: ``directives`` (what it may load) and no framing by other sites."""
    return f"{directives}; {FRAME_ANCESTORS}"


class SecurityHeadersMiddleware:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {key.lower() for key, _ in headers}
                headers += [(key, value) for key, value in HEADERS if key not in present]
                if CSP not in present:
                    headers.append((CSP, NOTHING_ALLOWED.encode()))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)
