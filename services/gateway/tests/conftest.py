"""What the gateway's tests share: a real gateway app under uvicorn on a free loopback port."""

from __future__ import annotations

import contextlib
import threading
import time

import pytest
import uvicorn

from twohr.bus import free_port
from twohr_services.gateway.app import create_app
from twohr_services.gateway.settings import GatewaySettings


@contextlib.contextmanager
def _served(settings: GatewaySettings, timeout: float = 30.0):
    """The gateway of ``settings`` served in a thread until the block ends; yields its base URL."""
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout
    while not server.started:
        assert time.monotonic() < deadline, "the gateway did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


@pytest.fixture
def serve_gateway():
    """``with serve_gateway(settings) as url:`` a real gateway on loopback for the block."""
    return _served
