"""Shared fixtures of the API tests: the main real server (see ``api_server.py``) and a client."""

from __future__ import annotations

import pytest
from api_server import main_server


@pytest.fixture(scope="session")
def server():
    """The main uvicorn server subprocess on 127.0.0.1 (started once per session)."""
    return main_server()


@pytest.fixture(scope="session")
def client(server):
    with server.client() as c:
        yield c
