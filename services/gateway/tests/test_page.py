"""The session page with an API token, in headless Chromium against a real gateway (uvicorn, Zenoh router).

No pipeline services run here: a started session stays 'starting' until it is stopped, which is all the
token handling needs."""

import threading
import time

import httpx
import pytest
import uvicorn
from playwright.sync_api import expect, sync_playwright

from twohr.bus import free_port
from twohr_services.gateway.app import GatewaySettings, create_app

TOKEN = "s3cret-token"


@pytest.fixture
def gateway(bus_config, dev_sequence, tmp_path):
    settings = GatewaySettings(data_roots=[dev_sequence.parent], recordings=tmp_path, api_token=TOKEN, bus=bus_config)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline, "the gateway did not start"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(10)


def test_page_sends_the_token_it_is_given(gateway, dev_sequence, tmp_path):
    index = httpx.get(gateway + "/")
    assert index.status_code == 200 and index.headers["content-type"].startswith("text/html")
    assert httpx.get(gateway + "/live").json() == {"foxglove_port": None}
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path="/usr/bin/chromium", headless=True)
        try:
            page = browser.new_page()
            page.goto(gateway + "/")
            expect(page.locator("#message")).to_contain_text("cannot list sessions: 401")
            expect(page.locator("#foxglove-link")).to_be_hidden()  # this gateway runs no live view
            page.fill("#sequence", dev_sequence.name)
            page.click("#start")
            expect(page.locator("#message")).to_contain_text("could not start: 401")
            page.fill("#token", TOKEN)
            page.click("#start")
            # the token is accepted: what stops the start now is that no pipeline service runs on this bus
            expect(page.locator("#message")).to_contain_text("could not start: 503: services not running")
            expect(page.locator("#message")).not_to_contain_text("401")
            page.screenshot(path=tmp_path / "token.png")
        finally:
            browser.close()
