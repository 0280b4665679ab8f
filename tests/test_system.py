"""The whole system as real processes on a real Zenoh router: gateway -> source -> cores -> tracker -> recorder.

One module-scoped stack serves every test here (start-up loads every model once per service).
"""

import re
import threading
import time

import httpx
import numpy as np
import pytest

from twohr import keys
from twohr.bus import BusConfig, free_port, open_session, query_health
from twohr.config import load_config
from twohr.dataset import RGBDSequence
from twohr.messages import PoseMsg, decode
from twohr.trajectory import read_tum
from twohr_app.pipeline import run_sequence
from twohr_app.supervisor import start_system
from twohr_services.recorder.core import topic_counts

FRAMES = 30  # a second of the camera, every frame a keyframe job, twice (the stack and one process)
# half-resolution R2D2 keeps this test quick; the same overrides go to `twohr run` below. The every-frame
# schedule is deterministic, so the bus and one process must agree exactly; the camera-rate schedule is
# tested at the end of this module.
OVERRIDES = {"detector.input_scale": 0.5, "pipeline.mode": "every_frame"}


@pytest.fixture(scope="module")
def system(tmp_path_factory, dev_sequence):
    recordings = tmp_path_factory.mktemp("recordings")
    router = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    stack = start_system(router, [str(dev_sequence.parent)], str(recordings), "127.0.0.1", port, timeout=180)
    yield {"router": router, "url": f"http://127.0.0.1:{port}", "recordings": recordings, "stack": stack}
    stack.stop()


class PoseListener:
    """An independent Zenoh client subscribed to every robot's poses (with the credentials of an outside
    client, which may read poses)."""

    def __init__(self, bus: BusConfig) -> None:
        self.session = open_session(bus)
        self.poses: list[tuple[str, PoseMsg]] = []
        self.lock = threading.Lock()
        self.sub = self.session.declare_subscriber(keys.all_robots("pose"), self._on)

    def _on(self, sample) -> None:
        pose, _ = decode(sample.payload.to_bytes(), PoseMsg)
        with self.lock:
            self.poses.append((str(sample.key_expr), pose))

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def wait_finished(client: httpx.Client, session_id: str, timeout: float = 600) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        info = client.get(f"/sessions/{session_id}").json()
        if info["state"] in ("finished", "stopped", "failed"):
            return info
        time.sleep(0.5)
    raise AssertionError(f"session {session_id} did not finish: {info}")


def test_post_session_streams_every_pose_and_matches_twohr_run(system, dev_sequence, tmp_path):
    listener = PoseListener(system["stack"].bus())
    try:
        with httpx.Client(base_url=system["url"], timeout=30) as client:
            response = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "robot_a",
                                                      "max_frames": FRAMES, "config": OVERRIDES})
            assert response.status_code == 201, response.text
            session_id = response.json()["id"]
            info = wait_finished(client, session_id)
            assert info["state"] == "finished" and info["frames"] == FRAMES, info
            served_response = client.get(f"/sessions/{session_id}/trajectory")
            online_response = client.get(f"/sessions/{session_id}/trajectory", params={"online": True})
            assert served_response.headers["x-twohr-trajectory"] == "refined"
            assert online_response.headers["x-twohr-trajectory"] == "online"
            info = client.get(f"/sessions/{session_id}").json()
            assert info["trajectory"] == "refined" and info["ate_rmse"] is not None and info["ate_rmse_online"]
            recording = client.get(f"/sessions/{session_id}/recording")
            assert recording.status_code == 200
    finally:
        time.sleep(0.5)
        listener.close()

    received = [p for k, p in listener.poses if p.session_id == session_id]
    assert sorted(p.frame_index for p in received) == list(range(FRAMES))
    assert all(k == "twohr/robot_a/pose" for k, p in listener.poses if p.session_id == session_id)

    # the same frames and config in one process give the same trajectories: online, and refined at the end
    local = run_sequence(RGBDSequence(dev_sequence), load_config(None, OVERRIDES), stop=FRAMES, progress=False)
    for response, expected in ((online_response, local.online), (served_response, local.trajectory)):
        (tmp_path / "served.txt").write_text(response.text)
        served = read_tum(tmp_path / "served.txt")
        assert np.allclose(served.stamps, expected.stamps)
        assert np.abs(served.positions - expected.positions).max() < 1e-6

    (tmp_path / "rec.mcap").write_bytes(recording.content)
    counts = topic_counts(tmp_path / "rec.mcap")
    for stream in ("keypoints", "dynamics", "pose"):
        assert counts[f"/twohr/robot_a/{stream}"] == FRAMES, (stream, counts)
    assert counts["/robot_a/path_refined"] == 1  # the refined trajectory, after the session's stop
    assert counts["/twohr/robot_a/matches"] >= FRAMES - 1
    assert counts["/robot_a/camera/image"] == FRAMES and counts["/tf"] == FRAMES


def test_bad_requests_get_clear_4xx(system, dev_sequence):
    with httpx.Client(base_url=system["url"], timeout=30) as client:
        cases = [
            ({"sequence": "/etc"}, 422, "not under the data roots"),
            ({"sequence": f"{dev_sequence.name}/../../shared"}, 422, "'..' is not allowed"),
            ({"robot_id": "r1"}, 422, "invalid request: give a sequence"),
            ({"sequence": dev_sequence.name, "config": {"detector.model": "nope"}}, 422,
             "unknown keyframe network 'nope'"),
            ({"sequence": dev_sequence.name, "config": {"yolo.model": "r2d2_WASF_N16"}}, 422, "not a YOLO"),
            ({"sequence": dev_sequence.name, "config": {"tracker.bogus": 1}}, 422, "tracker.bogus"),
            ({"sequence": dev_sequence.name, "robot_id": "bad id!"}, 422, "robot_id"),
            ({"sequence": dev_sequence.name, "rate": -1}, 422, "rate"),
            ({"sequence": dev_sequence.name, "config": {"yolo.dynamics_table": "/etc/passwd"}}, 422, "not a path"),
            ({"sequence": dev_sequence.name, "config": {"yolo.dynamics_table": "../t"}}, 422, "not a path"),
            ({"sequence": "missing_sequence"}, 422, "not found|not under"),
        ]
        for body, code, message in cases:
            response = client.post("/sessions", json=body)
            assert response.status_code == code, (body, response.text)
            assert re.search(message, response.json()["detail"]), (body, response.text)
        assert client.post("/sessions", content=b"{not json", headers={"content-type": "application/json"}
                           ).status_code == 422
        assert client.get("/sessions/nonexistent").status_code == 404
        assert client.delete("/sessions/nonexistent").status_code == 404
        assert client.get("/sessions/nonexistent/trajectory").status_code == 404
        assert client.get("/openapi.json").json()["paths"]["/sessions"]["post"]


def test_malformed_payloads_on_every_key_leave_services_alive(system):
    """Junk on every key, each sent by the role allowed to publish there (a compromised or buggy service):
    every service counts it as malformed and stays up."""
    publishers = {"frames": "source", "keypoints": "detector", "dynamics": "yolo", "matches": "matcher",
                  "pose": "tracker", "status": "source", keys.CONTROL: "gateway", keys.RAW_CAMERA: "client"}
    sessions = {role: open_session(system["stack"].bus(role)) for role in set(publishers.values())}
    try:
        for stream, role in publishers.items():
            for junk in (b"", b"junk", b"2HR\x01\x00\x00\x00\x10{}"):
                sessions[role].put(keys.key("robot_junk", stream), junk)
        replies = list(sessions["tracker"].get(keys.replica_query("robot_junk", keys.MATCH_QUERY, "*"), payload=b"junk",
                                               timeout=5))
        assert replies and replies[0].err is not None
        time.sleep(1.0)
        with httpx.Client(base_url=system["url"], timeout=30) as client:
            services = client.get("/healthz").json()["services"]
        for name, health in services.items():
            assert health is not None, f"{name} stopped answering"
            assert health["errors"] == 0, (name, health)
        # the detector hears control messages (3 junk), the tracker frames and control messages (6 junk)
        assert services["detector"]["malformed"] >= 3 and services["tracker"]["malformed"] >= 6
        assert services["recorder"]["malformed"] >= 3 and services["matcher"]["malformed"] >= 1
    finally:
        for session in sessions.values():
            session.close()


def test_two_robots_at_once_without_cross_talk(system, dev_sequence):
    listener = PoseListener(system["stack"].bus())
    try:
        with httpx.Client(base_url=system["url"], timeout=30) as client:
            ids = {}
            for robot, start_rate in (("robot_b", 0), ("robot_c", 0)):
                response = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": robot,
                                                          "max_frames": 12, "rate": start_rate, "record": False,
                                                          "config": OVERRIDES})
                assert response.status_code == 201, response.text
                ids[robot] = response.json()["id"]
            busy = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "robot_b",
                                                  "config": OVERRIDES})
            assert busy.status_code == 409
            infos = {robot: wait_finished(client, sid) for robot, sid in ids.items()}
    finally:
        time.sleep(0.5)
        listener.close()
    for robot, sid in ids.items():
        assert infos[robot]["frames"] == 12
        mine = [(k, p) for k, p in listener.poses if p.session_id == sid]
        assert sorted(p.frame_index for _, p in mine) == list(range(12))
        assert all(k == f"twohr/{robot}/pose" and p.robot_id == robot for k, p in mine)


def test_camera_rate_schedule_over_the_bus(system, dev_sequence, tmp_path):
    """The default schedule across Zenoh, the source playing at the camera's rate: every frame gets a pose
    from the tracker service (optical flow) or is counted as dropped because newer frames were waiting, and
    2HR detection runs only on the keyframes the tracker asks for."""
    frames = 90
    listener = PoseListener(system["stack"].bus())
    dropped_before = query_health(listener.session, "tracker")["dropped"]
    try:
        with httpx.Client(base_url=system["url"], timeout=30) as client:
            response = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "robot_k",
                                                      "max_frames": frames, "rate": 1.0})
            assert response.status_code == 201, response.text
            session_id = response.json()["id"]
            info = wait_finished(client, session_id)
            assert info["state"] == "finished" and info["frames_sent"] == frames, info
            recording = client.get(f"/sessions/{session_id}/recording")
            assert recording.status_code == 200
        tracker_health = query_health(listener.session, "tracker")
        dropped = tracker_health["dropped"] - dropped_before
    finally:
        time.sleep(0.5)
        listener.close()
    received = sorted((p.frame_index, p) for k, p in listener.poses if p.session_id == session_id)
    indices = [i for i, _ in received]
    assert len(set(indices)) == len(indices) and set(indices) <= set(range(frames))
    assert len(indices) + dropped == frames and len(indices) >= frames // 2, str((len(indices), tracker_health))
    assert info["frames_dropped"] == dropped, info  # the session status reports the drops
    statuses = [p.status for _, p in received]
    assert statuses[0] == "init" and statuses.count("tracking") >= 0.9 * (len(statuses) - 1), statuses
    assert info["ate_rmse"] < 0.05, info
    path = tmp_path / "camera_rate.mcap"
    path.write_bytes(recording.content)
    counts = topic_counts(path)
    assert counts["/robot_k/camera/image"] == frames and counts["/twohr/robot_k/pose"] == len(indices), counts
    # the detector ran on the keyframes the tracker asked for, not on every frame
    assert 1 <= counts.get("/twohr/robot_k/keypoints", 0) < frames / 2, counts
