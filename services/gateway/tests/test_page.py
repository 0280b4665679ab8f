"""The session page with an API token, in headless Chromium against a real gateway (uvicorn, Zenoh router).

No pipeline services run here: a started session stays 'starting' until it is stopped, which is all the
token handling needs."""


import httpx
import pytest
from playwright.sync_api import expect, sync_playwright

from twohr.dataset import RGBDSequence
from twohr.mapfile import write_map
from twohr_services.gateway.app import GatewaySettings

TOKEN = "s3cret-page-token"


@pytest.fixture
def gateway(bus_config, dev_sequence, tmp_path, tiny_map, serve_gateway):
    maps = tmp_path / "maps"
    write_map(maps / "lab.map", tiny_map("lab", RGBDSequence(dev_sequence).camera))
    (maps / "broken.map").write_bytes(b"not a map")
    settings = GatewaySettings(data_roots=[dev_sequence.parent], recordings=tmp_path, api_token=TOKEN, bus=bus_config,
                               maps=maps)
    with serve_gateway(settings) as url:
        yield url


def test_page_sends_the_token_it_is_given(gateway, dev_sequence, tmp_path):
    index = httpx.get(gateway + "/")
    assert index.status_code == 200 and index.headers["content-type"].startswith("text/html")
    assert httpx.get(gateway + "/live").json() == {"foxglove_port": None, "tls": False}
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


def test_page_lists_the_maps_and_starts_a_session_in_one(gateway, dev_sequence):
    """The maps of the store are listed (an unreadable file left out) and offered to a new session; the session
    request carries the chosen map and mode, and a new map's name, as the API checks them."""
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path="/usr/bin/chromium", headless=True)
        try:
            page = browser.new_page()
            page.goto(gateway + "/")
            page.fill("#token", TOKEN)
            expect(page.locator("#maps tr[data-map]")).to_have_count(1, timeout=10_000)
            expect(page.locator("#maps tr[data-map='lab']")).to_contain_text("1")
            expect(page.locator("#map-name option[value='lab']")).to_have_count(1)
            page.fill("#sequence", dev_sequence.name)
            page.fill("#start-frame", "5")
            page.select_option("#map-name", "lab")
            page.select_option("#map-mode", "localize")
            page.click("#start")
            # the map is usable: what stops the start is that no pipeline service runs on this bus
            expect(page.locator("#message")).to_contain_text("could not start: 503: services not running")
            page.select_option("#map-name", "__new__")
            expect(page.locator("#new-map")).to_be_visible()
            page.fill("#new-map", "no spaces allowed")
            page.click("#start")
            expect(page.locator("#message")).to_contain_text("422: invalid request: map.name")
        finally:
            browser.close()
    assert [m["name"] for m in httpx.get(gateway + "/maps", headers={"authorization": f"Bearer {TOKEN}"}).json()] == [
        "lab"]
