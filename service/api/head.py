"""HEAD answered as GET without the body (RFC 9110 9.3.2: a server that supports GET supports HEAD), for every GET
route at once: FastAPI routes answer only the methods they name, so load balancers' and uptime checkers' HEAD probes
of ``/v2/health/*`` got 405."""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.errors import HEAD_REQUEST
from service.api.middleware import HEAD_ERROR_BODY, MAX_ERROR_BODY_BYTES


class HeadAsGetMiddleware:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        def name_the_route() -> None:
            if "route" in as_get:  # the route GET matched: the access line and metrics name it
                scope["route"] = as_get["route"]

        async def send_headers_only(message: Message) -> None:
            if message["type"] == "http.response.start":
                status.append(message["status"])
            elif message["type"] == "http.response.body":  # the headers, Content-Length included, are GET's
                if status[0] >= 400:  # the error GET's body names, for the request context's access line
                    kept = scope["state"].setdefault(HEAD_ERROR_BODY, bytearray())
                    kept.extend(message.get("body", b"")[:MAX_ERROR_BODY_BYTES - len(kept)])
                message = {**message, "body": b""}
            name_the_route()  # before the last body goes out, where the request context counts the answer
            await send(message)

        status: list[int] = []
        scope.setdefault("state", {})[HEAD_REQUEST] = True  # the GET's 404/405 messages name HEAD
        as_get = {**scope, "method": "GET"}  # (the same ``state``)
        try:
            await self.app(as_get, receive, send_headers_only)
        finally:
            name_the_route()
