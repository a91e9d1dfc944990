"""HEAD answered as GET without the body (RFC 9110 9.3.2: a server that supports GET supports HEAD), for every GET
route at once: FastAPI routes answer only the methods they name, so load balancers' and uptime checkers' HEAD probes
of ``/v2/health/*`` got 405."""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send


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
            if message["type"] == "http.response.body":  # the headers, Content-Length included, are GET's
                message = {**message, "body": b""}
            name_the_route()  # before the last body goes out, where the request context counts the answer
            await send(message)

        as_get = {**scope, "method": "GET"}
        try:
            await self.app(as_get, receive, send_headers_only)
        finally:
            name_the_route()
