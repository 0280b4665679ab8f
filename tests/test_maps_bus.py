"""Maps on the bus and over HTTP: a session builds a map in the store (``twohr up --maps DIR``), another robot's
session localizes in it from where the first left off and publishes poses in its frame, the store survives the
stack being stopped and started again, and a broken map file is a 422 that breaks nothing else."""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest

from twohr import keys
from twohr.bus import free_port, open_session
from twohr.dataset import RGBDSequence
from twohr.evaluation import evaluate
from twohr.mapfile import read_map, verify_bytes
from twohr.mapstore import MapStore
from twohr.messages import PoseMsg, decode
from twohr.trajectory import Trajectory, read_tum
from twohr_app.supervisor import start_system

FAST = {"detector.input_scale": 0.5}


def _start(dev_sequence, recordings, maps):
    router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    stack = start_system(router, [str(dev_sequence.parent)], str(recordings), "127.0.0.1", port, timeout=180,
                         maps=str(maps))
    return stack, f"http://127.0.0.1:{port}"


def _run(client: httpx.Client, body: dict, timeout: float = 300) -> dict:
    response = client.post("/sessions", json=body)
    assert response.status_code == 201, response.text
    session_id = response.json()["id"]
    deadline = time.time() + timeout
    while time.time() < deadline:
        info = client.get(f"/sessions/{session_id}").json()
        if info["state"] not in ("starting", "running"):
            assert info["state"] == "finished", info
            return info
        time.sleep(0.5)
    raise AssertionError(f"session {session_id} did not finish")


def _wait_for_map(client: httpx.Client, name: str, version: int, timeout: float = 90) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        listed = {m["name"]: m for m in client.get("/maps").json()}
        if name in listed and listed[name]["version"] >= version:
            return listed[name]
        time.sleep(0.5)
    raise AssertionError(f"map {name} version {version} not in the store: {listed}")


def _trajectory(client: httpx.Client, session_id: str, tmp_path, name: str) -> Trajectory:
    (tmp_path / name).write_text(client.get(f"/sessions/{session_id}/trajectory").text)
    return read_tum(tmp_path / name)


@pytest.fixture
def frames_of():
    """Poses on twohr/<robot>/pose as an outside client reads them, by robot."""
    sessions, found = [], {}

    def listen(stack, robot: str) -> list[PoseMsg]:
        session = open_session(stack.bus("client"))
        poses: list[PoseMsg] = []
        lock = threading.Lock()

        def on(sample) -> None:
            with lock:
                poses.append(decode(sample.payload.to_bytes(), PoseMsg)[0])

        sessions.append((session, session.declare_subscriber(keys.key(robot, "pose"), on)))
        found[robot] = poses
        return poses

    yield listen
    for session, subscriber in sessions:
        subscriber.undeclare()
        session.close()


def test_a_map_built_by_one_robot_is_found_by_another_and_outlives_the_stack(dev_sequence, tmp_path, frames_of):
    maps, recordings = tmp_path / "maps", tmp_path / "recordings"
    sequence = RGBDSequence(dev_sequence)
    extrinsic = sequence.default_gt_extrinsic()
    stack, url = _start(dev_sequence, recordings, maps)
    try:
        with httpx.Client(base_url=url, timeout=60) as client:
            built = _run(client, {"sequence": dev_sequence.name, "robot_id": "a", "max_frames": 60,
                                  "map": {"name": "lab", "mode": "build"}, "config": FAST})
            entry = _wait_for_map(client, "lab", 1)
            assert entry["keyframes"] >= 2 and entry["landmarks"] > 100 and "session" in entry["built_by"]
            poses_b = frames_of(stack, "b")
            localized = _run(client, {"sequence": dev_sequence.name, "robot_id": "b", "start": 60, "max_frames": 40,
                                      "map": {"name": "lab", "mode": "localize"}, "config": FAST})
            assert localized["map"] == {"name": "lab", "mode": "localize"} and localized["start"] == 60
            assert localized["frames"] >= 36, localized  # posed: 90 % of the 40 frames
            time.sleep(0.5)
            assert poses_b and all(p.frame_id == "lab" for p in poses_b)
            assert min(p.frame_index for p in poses_b) >= 60
            a = _trajectory(client, built["id"], tmp_path, "a.txt")
            b = _trajectory(client, localized["id"], tmp_path, "b.txt")
            joined = Trajectory(np.concatenate([a.stamps, b.stamps]), np.concatenate([a.poses, b.poses]))
            report, _ = evaluate(sequence.ground_truth(extrinsic), joined, gt_extrinsic=extrinsic)
            assert report.ate.rmse < 0.03, report.ate.rmse  # one alignment: b's poses are in a's frame
            # localize leaves the map as it was
            assert client.get("/maps").json()[0]["version"] == 1

            # the store over HTTP: download, upload under another name, delete; a broken file is a 422
            data = client.get("/maps/lab").content
            assert verify_bytes(data).name == "lab"
            octets = {"content-type": "application/octet-stream"}
            renamed = client.post("/maps", params={"name": "copy"}, content=data, headers=octets)
            assert renamed.status_code == 422 and "holds map 'lab'" in renamed.json()["detail"]
            assert client.post("/maps", content=b"not a map", headers=octets).status_code == 422
            assert client.delete("/maps/copy").status_code == 404 and client.get("/maps/copy").status_code == 404
            (maps / "broken.map").write_bytes(b"PK broken")
            refused = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "c",
                                                     "map": {"name": "broken", "mode": "localize"}})
            assert refused.status_code == 422 and "broken" in refused.json()["detail"]
            missing = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "c",
                                                     "map": {"name": "nowhere", "mode": "extend"}})
            assert missing.status_code == 422 and "no map named" in missing.json()["detail"]
            assert [m["name"] for m in client.get("/maps").json()] == ["lab"]
    finally:
        stack.stop()

    # stopped and started again on the same folder: the map is still there, and a third robot finds itself in it
    assert read_map(maps / "lab.map").header.name == "lab"
    stack, url = _start(dev_sequence, recordings, maps)
    try:
        with httpx.Client(base_url=url, timeout=60) as client:
            assert [m["name"] for m in client.get("/maps").json()] == ["lab"]
            poses_c = frames_of(stack, "c")
            extended = _run(client, {"sequence": dev_sequence.name, "robot_id": "c", "start": 100, "max_frames": 30,
                                     "map": {"name": "lab", "mode": "extend"}, "config": FAST})
            assert extended["frames"] >= 27, extended
            time.sleep(0.5)
            assert poses_c and all(p.frame_id == "lab" for p in poses_c)
            entry = _wait_for_map(client, "lab", 2)  # extend: a new version; the first is kept beside it
            assert len(MapStore(maps).versions("lab")) == 1 and entry["keyframes"] >= read_map(
                maps / "lab.v1.map").header.keyframes
    finally:
        stack.stop()
