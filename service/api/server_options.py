"""``OPTIONS *`` answered for the server as a whole (RFC 9110 9.3.7: the asterisk-form target asks about the server,
not a resource): 200 with the methods its routes take in ``Allow``. It was a 404, and a load balancer checking health
with it (HAProxy's ``option httpchk OPTIONS *``) took the server for down."""

from __future__ import annotations

from types import SimpleNamespace

from starlette.types import ASGIApp, Receive, Scope, Send

SERVER_METHODS = "GET, HEAD, OPTIONS, POST"  # what some route of this server takes
SERVER_ROUTE = SimpleNamespace(path="*")  # the access line's and the metrics' route name


class ServerOptionsMiddleware:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "OPTIONS" or scope.get("path") != "*":
            await self.app(scope, receive, send)
            return
        scope["route"] = SERVER_ROUTE
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"allow", SERVER_METHODS.encode()), (b"content-length", b"0")]})
        await send({"type": "http.response.body", "body": b""})
