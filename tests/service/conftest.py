"""Shared fixtures of the service tests: the main real server (see ``api_server.py``), a client, and a model
folder for the command line."""

from __future__ import annotations

from pathlib import Path

import pytest
from api_server import main_server
from cli_support import snapshot_model


@pytest.fixture(scope="session")
def server():
    """The main uvicorn server subprocess on 127.0.0.1 (started once per session)."""
    return main_server()


@pytest.fixture(scope="session")
def client(server):
    with server.client() as c:
        yield c


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    """A copy of the bundled ``clean`` model, one per test module (a module may define its own)."""
    return snapshot_model(tmp_path_factory.mktemp("models"))
