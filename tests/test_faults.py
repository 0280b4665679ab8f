"""Faults and an attacker, on the secured stack that ``twohr up`` starts: spoofing, credentials, a killed
service, a config a service rejects, a killed recorder, bad HTTP input. Real router, real processes."""

import json
import os
import signal
import time

import httpx
import numpy as np
import pytest
from pydantic import SecretStr

from twohr import keys
from twohr.bus import BusConfig, free_port, open_session, wait_for_services
from twohr.errors import TwohrError
from twohr.messages import ControlMsg, PoseMsg, StatusMsg, encode
from twohr.trajectory import read_tum
from twohr_app.access import access_control, role_grants
from twohr_app.supervisor import start_system
from twohr_services.recorder.core import read_messages

TOKEN = "test-token-faults-1"
FAST = {"detector.input_scale": 0.5}
#: the poses a session has when a service of it is killed: its recording has a few messages by then (a fixed second
#: after its start had none on a CPU whose first keyframe takes that long)
MID_SESSION_POSES = 10


@pytest.fixture(scope="module")
def stack(tmp_path_factory, dev_sequence):
    recordings = tmp_path_factory.mktemp("recordings")
    port = free_port()
    system = start_system(f"tcp/127.0.0.1:{free_port()}", [str(dev_sequence.parent)], str(recordings), "127.0.0.1",
                          port, api_token=TOKEN, timeout=180)
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30,
                          headers={"Authorization": f"Bearer {TOKEN}"})
    yield {"system": system, "http": client, "recordings": recordings}
    client.close()
    system.stop()


def wait_state(client: httpx.Client, session_id: str, leave: tuple[str, ...], timeout: float) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = client.get(f"/sessions/{session_id}").json()
        if info["state"] not in leave:
            return info
        time.sleep(0.25)
    raise AssertionError(f"session {session_id} still {info['state']} after {timeout} s: {info}")


def start(client: httpx.Client, robot: str, dev_sequence, **body) -> str:
    response = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": robot, "config": FAST,
                                              **body})
    assert response.status_code == 201, response.text
    return response.json()["id"]


def fake_pose(session_id: str, robot: str, i: int) -> bytes:
    return encode(PoseMsg(session_id=session_id, robot_id=robot, frame_index=100_000 + i, stamp=1e6 + i,
                          position=[99.0, 99.0, 99.0], orientation=[0, 0, 0, 1], status="tracking"))


def test_access_control_grants_each_stream_to_one_kind_of_publisher():
    grants = role_grants()
    publishers = {stream: sorted(role for role, g in grants.items() if keys.all_robots(stream) in g.publish)
                  for stream in (*keys.STREAMS, keys.CONTROL, keys.RAW_CAMERA) if stream != "status"}
    assert publishers == {"pose": ["tracker"], "landmarks": ["tracker"], "path": ["tracker"], "control": ["gateway"],
                          "frames": ["source"], "keyframes": ["tracker"],
                          "keypoints": ["detector"], "dynamics": ["yolo"], "matches": ["matcher"],
                          "camera": ["client", "ros2", "router"]}
    assert "client" not in [r for r, g in grants.items() if keys.all_robots("status") in g.publish]
    acl = access_control()
    assert acl["default_permission"] == "deny" and {s["id"] for s in acl["subjects"]} == set(grants)


def test_no_credentials_no_bus(stack):
    endpoint = stack["system"].endpoint
    for user, password in ((None, None), ("client", "wrong"), ("nobody", "x")):
        bus = BusConfig(connect=[endpoint], user=user, password=SecretStr(password) if password else None,
                        config_file=None)
        with pytest.raises(TwohrError, match="cannot join the Zenoh bus"):
            open_session(bus).close()


def test_spoofed_poses_status_and_control_never_land(stack, dev_sequence, tmp_path):
    """The check's probe and its cousins: an outside client, a pipeline service in the wrong role, and the tracker
    speaking for another robot all try to inject poses, end the session or stop it. None lands."""
    system, client = stack["system"], stack["http"]
    session_id = start(client, "victim", dev_sequence, max_frames=90)
    wait_state(client, session_id, ("starting",), 120)
    sessions = {role: open_session(system.bus(role)) for role in ("client", "source", "tracker")}
    attempts = 0
    try:
        for i in range(5):  # the check: five poses from an outside client (with client credentials, even)
            sessions["client"].put(keys.key("victim", "pose"), fake_pose(session_id, "victim", i))
            sessions["source"].put(keys.key("victim", "pose"), fake_pose(session_id, "victim", 10 + i))
            sessions["tracker"].put(keys.key("other", "pose"), fake_pose(session_id, "victim", 20 + i))
            attempts += 3
        status = StatusMsg(session_id=session_id, robot_id="victim", frame_index=-1, stamp=time.time(),
                           service="source", state="error", detail="spoofed")
        stop = ControlMsg(session_id=session_id, robot_id="victim", frame_index=-1, stamp=time.time(),
                          command="stop")
        sessions["client"].put(keys.key("victim", "status"), encode(status))
        sessions["client"].put(keys.key("victim", keys.CONTROL), encode(stop))
        sessions["tracker"].put(keys.key("victim", keys.CONTROL), encode(stop))
        attempts += 3
        info = wait_state(client, session_id, ("starting", "running"), 300)
    finally:
        for session in sessions.values():
            session.close()
    assert info["state"] == "finished" and info["detail"] != "spoofed", info
    path = tmp_path / "trajectory.txt"
    path.write_text(client.get(f"/sessions/{session_id}/trajectory").text)
    trajectory = read_tum(path)
    assert len(trajectory) == info["frames"] == 90
    assert np.abs(trajectory.positions).max() < 10, "a spoofed pose landed"
    recording = client.get(f"/sessions/{session_id}/recording")
    assert recording.status_code == 200 and recording.headers["x-twohr-recording"] == "complete"
    (tmp_path / "rec.mcap").write_bytes(recording.content)
    recorded = [data for topic, data, _ in read_messages(tmp_path / "rec.mcap") if topic == "/twohr/victim/pose"]
    assert len(recorded) == info["frames"] and not any(b'"position":[99.0' in d for d in recorded)
    print(f"spoofing: {attempts} of {attempts} attempts blocked")


def test_bad_http_input_gets_4xx_and_documented_codes(stack, dev_sequence):
    client = stack["http"]
    cases = [
        (client.post("/sessions", json={"sequence": "x" * 5000}), 422),
        (client.post("/sessions", json={"sequence": "a/" * 400 + "b" * 300}), 422),
        (client.post("/sessions", json={"sequence": dev_sequence.name, "max_frames": 10**12}), 422),
        (client.post("/sessions", json={"sequence": dev_sequence.name, "config": {"detector.threads": 100000}}), 422),
        (client.post("/sessions", content=json.dumps({"sequence": dev_sequence.name, "config": {
            "detector.model": "y" * (5 << 20)}}), headers={"content-type": "application/json"}), 413),
        (httpx.get(f"{client.base_url}/sessions", headers={"Authorization": "Bearer ünïcode".encode()}), 401),
        (httpx.get(f"{client.base_url}/sessions"), 401),
    ]
    for response, code in cases:
        assert response.status_code == code, (response.request.url, response.text[:300])
        assert len(response.content) < 4000
    spec = client.get("/openapi.json").json()["paths"]
    assert {"401", "409", "413", "422", "503"} <= set(spec["/sessions"]["post"]["responses"])
    assert {"401", "404", "409"} <= set(spec["/sessions/{session_id}/recording"]["get"]["responses"])


def test_a_config_a_service_rejects_fails_the_session_at_once(stack, dev_sequence):
    client = stack["http"]
    t0 = time.monotonic()
    response = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "badcfg",
                                              "config": {"yolo.dynamics_table": "nosuchtable"}})
    assert response.status_code == 201, response.text
    info = wait_state(client, response.json()["id"], ("starting", "running"), 60)
    assert info["state"] == "failed" and info["detail"].startswith("yolo:"), info
    assert "nosuchtable" in info["detail"] and "not installed" in info["detail"]
    print(f"rejected config: failed after {time.monotonic() - t0:.1f} s")
    # the robot is free again
    assert client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "badcfg", "max_frames": 5,
                                          "config": FAST}).status_code == 201


@pytest.mark.parametrize("victim", ["detector", "tracker", "recorder"])
def test_a_killed_service_fails_its_session_and_comes_back(stack, dev_sequence, victim):
    """kill -9 a service mid-session: the session leaves `running` quickly with the reason, the gateway still
    answers, the service is restarted, and a new session on the same robot works."""
    system, client = stack["system"], stack["http"]
    robot = f"kill_{victim}"
    session_id = start(client, robot, dev_sequence, max_frames=300, rate=1.0)
    wait_state(client, session_id, ("starting",), 120)
    deadline = time.monotonic() + 60
    while client.get(f"/sessions/{session_id}").json()["frames"] < MID_SESSION_POSES:  # mid-session on any CPU
        assert time.monotonic() < deadline, f"{MID_SESSION_POSES} poses not within 60 s"
        time.sleep(0.1)
    os.kill(system.group.pid(victim), signal.SIGKILL)
    t0 = time.monotonic()
    info = wait_state(client, session_id, ("starting", "running"), 60)
    print(f"{victim} killed: session {info['state']} after {time.monotonic() - t0:.1f} s ({info['detail']})")
    assert info["state"] == "failed" and victim in info["detail"], info
    assert client.get("/healthz").status_code == 200
    bus = open_session(system.bus())
    try:
        wait_for_services(bus, [victim], timeout=180)
    finally:
        bus.close()
    deadline = time.monotonic() + 30
    while True:  # the gateway has seen the restarted service's liveliness token
        response = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": robot,
                                                  "max_frames": 15, "config": FAST})
        if response.status_code != 503 or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert response.status_code == 201, response.text
    after = wait_state(client, response.json()["id"], ("starting", "running"), 300)
    assert after["state"] == "finished" and after["frames"] == 15, after
    if victim == "recorder":
        recording = client.get(f"/sessions/{session_id}/recording")
        assert recording.status_code == 200 and recording.headers["x-twohr-recording"] == "partial"
        kept = json.loads((stack["recordings"] / f"{session_id}.partial.json").read_text())["messages"]
        print(f"recorder killed: {kept} messages recovered from its MCAP")
        assert kept > 0
