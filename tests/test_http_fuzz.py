"""The gateway's HTTP API under fuzzing (schemathesis, from its own OpenAPI spec) and under long requests.

A real gateway (uvicorn) on a real Zenoh router. No pipeline runs: stand-ins announce the services' liveliness
tokens on the bus, so the gateway accepts sessions (they stay ``starting``) and every route is reachable."""

from __future__ import annotations

import statistics
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
import schemathesis
import uvicorn
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable
from mcap.writer import Writer
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)
from schemathesis.core.failures import Failure, FailureGroup

from twohr import keys
from twohr.bus import free_port, open_session
from twohr.dataset import RGBDSequence
from twohr.keys import PIPELINE_SERVICES
from twohr.mapfile import write_map
from twohr.mcapfile import MCAP_MAGIC
from twohr_services.gateway.app import GatewaySettings, create_app

TOKEN = "http-fuzz-token-1"
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
CASES_PER_OPERATION = 40


@pytest.fixture(scope="module")
def gateway(zenoh_router, dev_sequence, tmp_path_factory, tiny_map):
    from twohr.bus import BusConfig

    bus = BusConfig(connect=[zenoh_router])
    stand_in = open_session(bus)
    tokens = [stand_in.liveliness().declare_token(keys.alive_key(name, "stand-in")) for name in PIPELINE_SERVICES]
    recordings = tmp_path_factory.mktemp("recordings")
    maps = tmp_path_factory.mktemp("maps")  # a map store with one map, for the /maps routes and session maps
    write_map(maps / "lab.map", tiny_map("lab", RGBDSequence(dev_sequence).camera))
    # no pipeline runs, so no refined path ever comes: a recording the recorder has opened is waited for 10 s and
    # refine_timeout more (30 s by default), here 1 s
    settings_ = GatewaySettings(data_roots=[dev_sequence.parent], recordings=recordings, api_token=TOKEN, bus=bus,
                                maps=maps, refine_timeout=1.0)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings_), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while True:  # up, and it has seen every stand-in's liveliness token
        assert time.monotonic() < deadline, "the gateway did not start"
        if server.started and httpx.post(f"{url}/sessions", headers={"Authorization": f"Bearer {TOKEN}"},
                                         json={"sequence": dev_sequence.name, "robot_id": "probe"}).status_code == 201:
            break
        time.sleep(0.1)
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        ended = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "ended"}).json()["id"]
        client.delete(f"/sessions/{ended}")
        with open(recordings / f"{ended}.mcap", "wb") as fh:  # a finalised (empty) recording
            writer = Writer(fh)
            writer.start()
            writer.finish()
        active = client.get("/sessions").json()[0]["id"]
    yield {"url": url, "recordings": recordings, "sessions": [active, ended]}
    server.should_exit = True
    thread.join(10)
    for token in tokens:
        token.undeclare()
    stand_in.close()


#: the callers the fuzzer plays: with the API token and without any
CALLERS = {"token": {"Authorization": f"Bearer {TOKEN}"}, "no-token": {}}


def fuzz(url: str, mode: schemathesis.GenerationMode, session_ids: list[str]) -> dict[str, tuple[Counter, list]]:
    """Run schemathesis cases of every operation (paths with a session id: random ids and real ones), each case sent
    by every caller of :data:`CALLERS` (generating a case costs more than sending it); count each caller's cases,
    status classes and check failures."""
    schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
    found = {caller: (Counter(), []) for caller in CALLERS}
    for result in schema.get_all_operations():
        operation = result.ok()
        strategies = [operation.as_strategy(generation_mode=mode)]
        if "{session_id}" in operation.path:
            strategies += [operation.as_strategy(generation_mode=mode, path_parameters={"session_id": sid})
                           for sid in session_ids]

        @settings(max_examples=CASES_PER_OPERATION, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(case=st.one_of(strategies))
        def run(case):
            for caller, headers in CALLERS.items():
                tally, problems = found[caller]
                response = case.call(base_url=url, headers=headers, timeout=30)
                tally["cases"] += 1
                tally[f"{case.operation.label} {response.status_code}"] += 1
                tally[f"{response.status_code // 100}xx"] += 1
                try:
                    case.validate_response(response, checks=CHECKS)
                except (Failure, FailureGroup) as exc:
                    tally["violations"] += 1
                    problems.append(f"{case.method} {case.formatted_path} -> {response.status_code}: "
                                    f"{' | '.join(str(exc).strip().splitlines()[:12])}")

        try:
            run()
        except Unsatisfiable:  # nothing to break in an operation without parameters: no negative cases
            assert mode == schemathesis.GenerationMode.NEGATIVE, operation.label
    return found


@pytest.fixture(scope="module")
def fuzzed(gateway) -> dict[str, tuple[Counter, list]]:
    """Each caller's tally and problems over both generation modes: one fuzzing pass serves both tests below."""
    found = {caller: (Counter(), []) for caller in CALLERS}
    for mode in (schemathesis.GenerationMode.POSITIVE, schemathesis.GenerationMode.NEGATIVE):
        for caller, (tally, problems) in fuzz(gateway["url"], mode, gateway["sessions"]).items():
            found[caller][0].update(tally)
            found[caller][1].extend(problems)
    return found


@pytest.mark.parametrize("caller", list(CALLERS))
def test_schemathesis_finds_no_5xx_and_no_undocumented_response(fuzzed, caller):
    total, problems = fuzzed[caller]
    print(f"schemathesis ({'with' if caller == 'token' else 'without'} token): {dict(total)}")
    assert total["cases"] >= 200
    assert total["5xx"] == 0 and not problems, "\n".join(sorted(set(problems))[:20])
    answered = {tuple(key.rsplit(" ", 1)) for key in total if key.startswith(("GET ", "POST ", "DELETE "))}
    if caller == "no-token":  # only the page's routes and the gateway's liveness answer without the token
        assert {label for label, code in answered if code.startswith("2")} <= {"GET /live", "GET /healthz"}
    else:
        assert "401" not in {code for _, code in answered} and total["2xx"] >= 5


def test_long_recording_requests_leave_the_gateway_responsive(gateway, dev_sequence):
    """45 concurrent GET /recording of an ended session whose MCAP the recorder has not finalised each wait for
    it (10 s and the gateway's refine_timeout, 1 s here); meanwhile GET /sessions answers at once."""
    url, auth = gateway["url"], {"Authorization": f"Bearer {TOKEN}"}
    with httpx.Client(base_url=url, headers=auth, timeout=60) as client:
        created = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "longreq"})
        assert created.status_code == 201, created.text
        session_id = created.json()["id"]
        assert client.delete(f"/sessions/{session_id}").json()["state"] == "stopped"
        (gateway["recordings"] / f"{session_id}.mcap").write_bytes(MCAP_MAGIC + b"\x01" * 1000)  # mid-write

        def download(_):
            t0 = time.monotonic()
            response = httpx.get(f"{url}/sessions/{session_id}/recording", headers=auth, timeout=60)
            return response.status_code, time.monotonic() - t0

        with ThreadPoolExecutor(45) as pool:
            downloads = [pool.submit(download, i) for i in range(45)]
            time.sleep(1.0)  # every request is in and waiting
            lists = []
            for _ in range(10):
                t0 = time.monotonic()
                assert client.get("/sessions").status_code == 200
                lists.append(time.monotonic() - t0)
                time.sleep(0.3)
            results = [d.result() for d in downloads]
    median = statistics.median(lists)
    print(f"GET /sessions during 45 waiting GET /recording: median {median * 1000:.0f} ms, max "
          f"{max(lists) * 1000:.0f} ms; the downloads answered {Counter(code for code, _ in results)} after "
          f"{min(t for _, t in results):.1f}-{max(t for _, t in results):.1f} s")
    assert all(code == 409 for code, _ in results), results
    assert all(t >= 9 for _, t in results), "the downloads must still have been waiting while /sessions was timed"
    assert median < 1.0 and max(lists) < 3.0  # generous: a route stuck behind the waits takes 10 s
