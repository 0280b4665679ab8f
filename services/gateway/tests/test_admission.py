"""Admission over real HTTP: a gateway (uvicorn) that carries two robots at 30 Hz takes two camera sessions, answers
a third with 503, ``Retry-After`` and one line, and takes robots admitted at half rate into a free share. The
pipeline services are stand-ins that hold their liveliness tokens on a real router (no session runs here)."""

from __future__ import annotations

import threading
import time

import httpx
import pytest
import uvicorn

from twohr import keys
from twohr.bus import BusConfig, free_port, open_session
from twohr.errors import ConfigError
from twohr.keys import PIPELINE_SERVICES
from twohr_services.gateway.admission import parse_max_robots, session_load
from twohr_services.gateway.app import create_app
from twohr_services.gateway.sessions import SessionRequest
from twohr_services.gateway.settings import GatewaySettings


@pytest.fixture
def gateway(zenoh_router, dev_sequence, tmp_path):
    bus = BusConfig(connect=[zenoh_router])
    stand_in = open_session(bus)
    tokens = [stand_in.liveliness().declare_token(keys.alive_key(name, "stand-in")) for name in PIPELINE_SERVICES]
    settings = GatewaySettings(data_roots=[dev_sequence.parent], recordings=tmp_path, bus=bus, max_robots=2)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30)
    deadline = time.monotonic() + 30
    while not server.started or client.get("/healthz").status_code != 200 or client.post(
            "/sessions", json={"source": "camera", "robot_id": "probe", "rate": 1}).status_code != 201:
        assert time.monotonic() < deadline, "the gateway did not start"
        time.sleep(0.1)
    client.delete(f"/sessions/{client.get('/sessions').json()[0]['id']}")
    yield client
    client.close()
    server.should_exit = True
    thread.join(10)
    for token in tokens:
        token.undeclare()
    stand_in.close()


def camera(client: httpx.Client, robot: str, rate: float = 0) -> httpx.Response:
    return client.post("/sessions", json={"source": "camera", "robot_id": robot, "rate": rate, "record": False})


def test_past_its_capacity_the_stack_answers_503_with_retry_after_and_takes_lower_rates(gateway):
    first, second = camera(gateway, "r1"), camera(gateway, "r2")
    assert (first.status_code, second.status_code) == (201, 201), (first.text, second.text)
    third = camera(gateway, "r3")
    assert third.status_code == 503 and third.headers["retry-after"] == "30", third.text
    detail = third.json()["detail"]
    assert detail.startswith("the stack is full: it carries 2 robots at 30 Hz (--max-robots) and runs 2;")
    assert "\n" not in detail
    assert camera(gateway, "r3", rate=15).status_code == 503  # half a share does not fit either
    assert gateway.delete(f"/sessions/{second.json()['id']}").status_code == 200
    # one share free: two robots at 15 Hz fit in it, a third at 1 Hz does not
    halves = [camera(gateway, robot, rate=15) for robot in ("r3", "r4")]
    assert [h.status_code for h in halves] == [201, 201], [h.text for h in halves]
    assert camera(gateway, "r5", rate=1).status_code == 503
    assert gateway.delete(f"/sessions/{halves[0].json()['id']}").status_code == 200
    offered = camera(gateway, "r5")  # a full share no longer fits: it is told the rate that does
    assert offered.status_code == 503 and 'ask for "rate": 15 (Hz)' in offered.json()["detail"], offered.text


def test_a_negative_rate_is_one_clear_error(gateway):
    answer = camera(gateway, "r1", rate=-1)
    assert answer.status_code == 422
    detail = answer.json()["detail"]
    assert detail.startswith("invalid request: rate: ") and "greater than or equal to 0" in detail, detail
    assert "\n" not in detail


def test_what_a_session_weighs():
    assert session_load(SessionRequest(source="camera")) == 1.0
    assert session_load(SessionRequest(source="camera", rate=15)) == 0.5
    assert session_load(SessionRequest(source="camera", rate=60)) == 1.0  # no robot weighs more than its camera
    assert session_load(SessionRequest(sequence="s", rate=2)) == 2.0  # a replay at twice real time: two cameras
    assert session_load(SessionRequest(sequence="s", rate=0)) == 1.0


def test_the_gateway_alone_reads_a_count_and_refuses_auto_in_one_line():
    """``auto`` is what ``twohr up`` measures on its host; the gateway alone cannot, and says so."""
    assert parse_max_robots("2") == 2.0 and parse_max_robots("1.5") == 1.5
    with pytest.raises(ConfigError) as refused:
        parse_max_robots("auto")
    line = str(refused.value)
    assert "\n" not in line and "twohr up" in line and "--max-robots N" in line
    with pytest.raises(ConfigError):
        parse_max_robots("0")
