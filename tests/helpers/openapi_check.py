"""Check a real HTTP response against what ``/openapi.json`` declares for its operation, status and content type."""

from __future__ import annotations

import httpx
from jsonschema import Draft202012Validator


def declared_response(doc: dict, method: str, path: str, status: int) -> dict:
    """The response object ``doc`` declares for ``method path`` (path as in the document: ``/v2/models/{name}``)
    and ``status``; fails naming the declared statuses when there is none."""
    operation = doc["paths"][path][method.lower()]
    declared = operation["responses"]
    assert str(status) in declared, f"{method} {path} answered {status}, declared only {sorted(declared)}"
    return declared[str(status)]


def assert_conforms(doc: dict, method: str, path: str, response: httpx.Response) -> None:
    """``response`` has a declared status and content type, its JSON body validates against the declared schema
    (components resolved, JSON Schema 2020-12 as OpenAPI 3.1 uses), and the headers the server sends that the
    document names for some response (``WWW-Authenticate``, ``Retry-After``) are declared for this one."""
    declared = declared_response(doc, method, path, response.status_code)
    media = response.headers.get("content-type", "").split(";", 1)[0].strip()
    content = declared.get("content", {})
    assert media in content, f"{method} {path} {response.status_code}: {media!r} not declared (only {list(content)})"
    schema = content[media].get("schema")
    assert schema, f"{method} {path} {response.status_code} {media}: no schema declared"
    if media == "application/json":
        validator = Draft202012Validator({**schema, "components": doc["components"]})
        errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message[:200]}" for e in validator.iter_errors(
            response.json())]
        assert not errors, f"{method} {path} {response.status_code}: body breaks the declared schema: {errors[:5]}"
    for header in ("WWW-Authenticate", "Retry-After"):
        if header.lower() in response.headers:
            assert header in declared.get("headers", {}), f"{method} {path} {response.status_code}: {header} sent, " \
                "not declared"
