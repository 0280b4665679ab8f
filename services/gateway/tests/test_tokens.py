"""The gateway's one token check (``tokens.Tokens``, the HTTP API's and the live view's): a blank or short operator
token is refused wherever it is set, a robot's token stops working when its certificate expires (``not_after`` in
the tokens file; the earlier ``{robot: digest}`` file is still read), and a live view token opens nothing of the
HTTP API. A real gateway (uvicorn, a Zenoh router) on a real fleet's keys folder; the gateway and ``twohr keys``
as processes for the refusals."""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import subprocess
import sys
import time

import httpx
import pytest
from pydantic import ValidationError

from twohr.bus import free_port
from twohr_app.fleet import Fleet
from twohr_services.gateway.app import GatewaySettings
from twohr_services.gateway.tokens import Tokens, view_token

OPERATOR = "operator-token-of-the-tokens-test"
BRIEF_S = 4.0  # robot "brief"'s certificate, and so its token, lasts this long
ENV = {k: v for k, v in os.environ.items() if k != "TWOHR_API_TOKEN"}


@pytest.fixture
def fleet(tmp_path):
    """A fleet with robot a (a year) and robot brief (a few seconds); their API tokens."""
    made = Fleet(tmp_path / "K")
    made.init(api_token=OPERATOR)
    tokens = {robot: made.add(robot, tmp_path / f"{robot}.bundle", days=days).api_token.get_secret_value()
              for robot, days in (("a", 365), ("brief", BRIEF_S / 86400))}
    return made, tokens


@pytest.fixture
def gateway(fleet, bus_config, tmp_path, serve_gateway):
    settings = GatewaySettings(api_token=OPERATOR, robot_tokens=fleet[0].service_folder("gateway") / "tokens.json",
                               recordings=tmp_path / "recordings", bus=bus_config)
    with serve_gateway(settings) as url:
        yield url


def status(gateway: str, token: str | None) -> int:
    """What ``GET /sessions`` answers to ``token`` (None: no Authorization header)."""
    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    return httpx.get(gateway + "/sessions", headers=headers, timeout=10).status_code


def test_an_expired_robots_token_is_refused_and_a_view_token_is_no_api_token(gateway, fleet):
    fleet, tokens = fleet
    path = fleet.service_folder("gateway") / "tokens.json"
    written = json.loads(path.read_text())
    assert set(written["brief"]) == {"sha256", "not_after"}
    until = datetime.datetime.fromisoformat(written["brief"]["not_after"])
    assert 0 < (until - datetime.datetime.now(datetime.timezone.utc)).total_seconds() <= BRIEF_S + 1
    assert [status(gateway, t) for t in (OPERATOR, tokens["a"], tokens["brief"])] == [200, 200, 200]
    # no token, an empty one, a view token (the live view's, of a valid API token): none is an API token
    assert [status(gateway, t) for t in (None, view_token(OPERATOR), view_token(tokens["a"]))] == [401] * 3
    assert httpx.get(gateway + "/sessions", headers={"Authorization": "Bearer"}).status_code == 401

    while datetime.datetime.now(datetime.timezone.utc) <= until:
        time.sleep(0.2)
    assert status(gateway, tokens["brief"]) == 401 and status(gateway, tokens["a"]) == 200
    # the live view's check is the same one: brief is out there too, a's view token still opens it
    check = Tokens(OPERATOR, path)
    assert check.identify_viewer(view_token(tokens["brief"])) is None and check.identify(tokens["brief"]) is None
    assert check.identify_viewer(view_token(tokens["a"])).robot == "a" and check.identify_viewer(
        view_token(OPERATOR)).robot is None

    # a tokens file as twohr keys wrote it before expiry was recorded: read as it is, no expiry
    path.write_text(json.dumps({"brief": hashlib.sha256(tokens["brief"].encode()).hexdigest()}))
    assert status(gateway, tokens["brief"]) == 200 and status(gateway, tokens["a"]) == 401


def one_line(done: subprocess.CompletedProcess) -> str:
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    return lines[0]


def test_a_blank_or_short_operator_token_is_refused(tmp_path):
    for token in ("", "   ", "short-token", "sixteen chars ok"):
        with pytest.raises(ValidationError, match="API token"):
            GatewaySettings(api_token=token)
    assert GatewaySettings(api_token="x" * 16).api_token == "x" * 16
    empty = tmp_path / "operator.token"
    empty.write_text("\n")
    done = subprocess.run([sys.executable, "-m", "twohr_services.gateway", "--api-token-file", str(empty), "--port",
                           str(free_port())], capture_output=True, text=True, timeout=60, env=ENV)
    assert "the API token is empty" in one_line(done)
    done = subprocess.run([sys.executable, "-m", "twohr_app", "keys", "init", str(tmp_path / "K")],
                          capture_output=True, text=True, timeout=60, env=ENV | {"TWOHR_API_TOKEN": "short"})
    assert "TWOHR_API_TOKEN" in one_line(done) and not (tmp_path / "K" / "ca.key").exists()
