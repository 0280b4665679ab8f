"""Maps are owned, rolled back and audited (issue 49, items 2 and 8), with a whole stack on a fleet's keys as the
operator runs it: ``twohr keys init``, ``twohr keys add``, ``twohr up --keys`` (mutual TLS, HTTPS, one API token per
robot, the operator's in ``K/operator.token``), SLAM sessions on the real dev frames, and ``twohr keys grant`` /
``twohr keys revoke`` while it runs.

Robot ``a`` builds map ``lab``: the tracker saves it and the gateway records ``a`` as its owner. Robot ``b`` may
localize in it at once, but its ``extend`` is a 403 (one line) until the operator grants it; then the same request
is accepted and its session saves version 2, still owned by ``a`` alone with ``b`` among its contributors: once the
operator takes the grant back (``keys grant --remove``), ``b``'s extend is a 403 again. The operator rolls ``lab``
back to version 1 over HTTP: the served bytes are version 1's. ``GET /audit`` shows all of it, with the times, to the
operator; a robot's token gets 403."""

from __future__ import annotations

import json
import os
import signal
import ssl
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from twohr.bus import free_port
from twohr.mapfile import OPERATOR, read_map
from twohr.paths import DEV_SEQUENCE

FAST = {"detector.input_scale": 0.5}
SEQUENCE = Path(DEV_SEQUENCE).name  # the dev sequence's folder, under the stack's data root


def twohr(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def stack(tmp_path_factory, dev_sequence):
    """``twohr up --keys K --maps M`` as a process, with robots a, b and c; yields what the test needs."""
    tmp = tmp_path_factory.mktemp("owned_maps")
    keys = tmp / "K"
    for args in (["init", str(keys)], *[["add", str(keys), robot, "--out", str(tmp / f"{robot}.bundle")]
                                        for robot in ("a", "b", "c")]):
        done = twohr("keys", *args)
        assert done.returncode == 0, done.stderr
    port, log = free_port(), tmp / "up.log"
    with open(log, "w") as out:
        up = subprocess.Popen([sys.executable, "-m", "twohr_app", "up", "--keys", str(keys), "--router",
                               f"tls/127.0.0.1:{free_port()}", "--port", str(port), "--maps", str(tmp / "maps"),
                               "--recordings", str(tmp / "recordings"), "--data-root", str(dev_sequence.parent),
                               "--foxglove-port", "0", "--max-robots", "2", "--timeout", "240"],
                              stdout=out, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while "all healthy" not in log.read_text():
            assert up.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.2)
        tokens = {robot: json.loads((tmp / f"{robot}.bundle").read_text())["api_token"] for robot in "abc"}
        tokens[OPERATOR] = (keys / "operator.token").read_text().strip()
        yield {"url": f"https://127.0.0.1:{port}", "keys": keys, "tmp": tmp, "tokens": tokens}
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait()


def client(stack, who: str) -> httpx.Client:
    """An HTTPS client of the gateway with ``who``'s token (a robot id, or the operator), verified with the CA."""
    return httpx.Client(base_url=stack["url"], timeout=60,
                        verify=ssl.create_default_context(cafile=str(stack["keys"] / "ca.crt")),
                        headers={"Authorization": f"Bearer {stack['tokens'][who]}"})


def session(http: httpx.Client, robot: str, start: int, frames: int, name: str, mode: str) -> httpx.Response:
    return http.post("/sessions", json={"sequence": SEQUENCE, "robot_id": robot, "start": start,
                                        "max_frames": frames, "record": False, "config": FAST,
                                        "map": {"name": name, "mode": mode}})


def finished(http: httpx.Client, session_id: str, timeout: float = 400) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = http.get(f"/sessions/{session_id}").json()
        if info["state"] not in ("starting", "running"):
            assert info["state"] == "finished", info
            return info
        time.sleep(0.5)
    raise AssertionError(f"session {session_id} did not finish")


def map_version(http: httpx.Client, name: str, version: int, timeout: float = 90) -> dict:
    """The store's entry of map ``name`` once its latest version is ``version`` (the tracker saves after the end)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        listed = {m["name"]: m for m in http.get("/maps").json()}
        if listed.get(name, {}).get("version") == version:
            return listed[name]
        time.sleep(0.5)
    raise AssertionError(f"map {name} version {version} not in the store: {listed}")


def test_a_map_is_its_builders_until_the_operator_grants_it_and_rolls_back(stack, dev_sequence):
    with client(stack, OPERATOR) as operator, client(stack, "a") as a, client(stack, "b") as b:
        built = session(a, "a", 0, 40, "lab", "build")
        assert built.status_code == 201, built.text
        finished(a, built.json()["id"])
        first = map_version(operator, "lab", 1)
        assert first["owners"] == ["a"] and first["keyframes"] >= 2 and first["versions"] == [1]
        version_1 = operator.get("/maps/lab").content
        assert read_map(version_1).header.owners == ["a"]

        # localize needs no grant (b stops it at once); extend does
        localized = session(b, "b", 30, 20, "lab", "localize")
        assert localized.status_code == 201, localized.text
        assert b.delete(f"/sessions/{localized.json()['id']}").json()["state"] == "stopped"
        refused = session(b, "b", 30, 20, "lab", "extend")
        assert refused.status_code == 403 and "\n" not in refused.json()["detail"], refused.text
        assert "owned by a" in refused.json()["detail"] and "twohr keys grant" in refused.json()["detail"]
        assert session(b, "b", 30, 20, "lab", "build").status_code == 403  # nor may it build over it

        granted = twohr("keys", "grant", str(stack["keys"]), "b", "--map", "lab")
        assert granted.returncode == 0, granted.stderr
        extended = session(b, "b", 30, 20, "lab", "extend")
        assert extended.status_code == 201, extended.text
        finished(b, extended.json()["id"])
        second = map_version(operator, "lab", 2)
        assert second["owners"] == ["a"] and second["contributors"] == ["b"] and second["versions"] == [1, 2]
        # the grant was the authority, not the change b made under it: taken back, b is refused again
        removed = twohr("keys", "grant", str(stack["keys"]), "b", "--map", "lab", "--remove")
        assert removed.returncode == 0, removed.stderr
        again = session(b, "b", 30, 20, "lab", "extend")
        assert again.status_code == 403 and "owned by a" in again.json()["detail"], again.text
        assert operator.get("/maps/lab").content != version_1
        assert operator.get("/maps/lab", params={"version": 1}).content == version_1

        # the rollback: the operator's only, and the served bytes are version 1's again
        assert b.post("/maps/lab/rollback", params={"version": 1}).status_code == 403
        rolled = operator.post("/maps/lab/rollback", params={"version": 1})
        assert rolled.status_code == 200 and rolled.json()["version"] == 3 and rolled.json()["owners"] == ["a"]
        assert operator.get("/maps/lab").content == version_1 and b.get("/maps/lab").content == version_1
        assert operator.post("/maps/lab/rollback", params={"version": 7}).status_code == 404
        assert operator.post("/maps/lab/rollback", params={"version": 3}).status_code == 409

        revoked = twohr("keys", "revoke", str(stack["keys"]), "c", timeout=60)
        assert revoked.returncode == 0, revoked.stderr

        # the audit trail: the operator's only
        for robot in (a, b):
            denied = robot.get("/audit")
            assert denied.status_code == 403 and "operator's token" in denied.json()["detail"]
        deadline = time.monotonic() + 10
        events = operator.get("/audit").json()
        while not any(e["action"] == "robot.revoke" for e in events):
            assert time.monotonic() < deadline, events
            time.sleep(0.25)
            events = operator.get("/audit").json()
    said = [(e["action"], e["who"], e.get("robot"), e.get("map"), e.get("version")) for e in events]
    assert said[:2] == [("session.start", "a", "a", "lab", None), ("session.finish", "@stack", "a", None, None)]
    expected = [("map.save", "a", "a", "lab", 1),
                ("session.start", "b", "b", "lab", None), ("session.stop", "b", "b", None, None),
                ("map.grant", OPERATOR, "b", "lab", None),
                ("session.start", "b", "b", "lab", None), ("map.save", "b", "b", "lab", 2),
                ("map.ungrant", OPERATOR, "b", "lab", None),
                ("map.rollback", OPERATOR, None, "lab", 3), ("robot.revoke", OPERATOR, "c", None, None)]
    assert [event for event in said if event in expected] == expected, said
    times = [e["time"] for e in events]
    assert times == sorted(times) and all(e["utc"].endswith("+00:00") for e in events)
    assert time.time() - 900 < times[0] <= times[-1] <= time.time()
    log = stack["tmp"] / "maps" / "audit.jsonl"  # twohr up keeps it in the map store, where twohr maps rollback appends
    assert not (stack["tmp"] / "recordings" / "audit.jsonl").exists()
    assert log.stat().st_mode & 0o777 == 0o600 and len(log.read_text().splitlines()) == len(events)
