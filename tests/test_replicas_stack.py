"""Replicas in a running stack: ``twohr up --replicas detector=2,tracker=2`` shares the keyframe jobs of a live session
between two detector processes; one killed with SIGKILL mid-session loses no job (the one in flight goes to the
other) and comes back as the same replica once its supervisor restarts it; ``twohr health`` lists both with their
host and process id. Two robots at once each get a tracker of their own, which names the robot it serves, and only
that one tracks its frames; a tracker killed hands its robot to the other tracker, in the robot's map. Bad
``--replicas`` and ``--join`` input is one clear line each."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from twohr.bus import free_port, open_session, query_health
from twohr_app.supervisor import start_system

FAST = {"detector.input_scale": 0.5}
RECORDED_HZ = 30.0  # the dev frames' rate: a replay's rate is a factor of it
TWOHR = Path(sys.executable).with_name("twohr")


@pytest.fixture(scope="module")
def stack(tmp_path_factory, dev_sequence):
    router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    system = start_system(router, [str(dev_sequence.parent)], str(tmp_path_factory.mktemp("recordings")),
                          "127.0.0.1", port, timeout=180, replicas={"detector": 2, "tracker": 2})
    session = open_session(system.bus("gateway"))
    yield {"system": system, "url": f"http://127.0.0.1:{port}", "router": router, "bus": session}
    session.close()
    system.stop()


def detector_jobs(stack) -> dict:
    return query_health(stack["bus"], "tracker", timeout=2.0)["jobs"]["detector"]


def tracker_child(replica: str) -> str:
    """The supervisor's child name (``tracker``, ``tracker-2``) of a tracker replica this test process started."""
    return replica.split(f"-{os.getpid()}-", 1)[1]


def wait_until(condition, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        assert time.monotonic() < deadline, f"{what} not within {timeout} s"
        time.sleep(0.1)
    return value


def test_two_detector_replicas_share_the_jobs_and_one_killed_loses_none(stack, dev_sequence):
    before = detector_jobs(stack)
    replicas = sorted(before["alive"])
    assert len(replicas) == 2, before
    with httpx.Client(base_url=stack["url"], timeout=30) as http:
        created = http.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "replicas", "rate": 1.0,
                                               "record": False, "config": FAST})
        assert created.status_code == 201, created.text
        sid = created.json()["id"]

        def answered_by_both():
            jobs = detector_jobs(stack)["answered"]
            return jobs if all(jobs.get(r, 0) > before["answered"].get(r, 0) for r in replicas) else None

        split = wait_until(answered_by_both, 60, "keyframe jobs on both replicas")
        victim = stack["system"].group.pid("detector-2")
        os.kill(victim, signal.SIGKILL)
        time.sleep(4.0)  # keyframes go on, on the other replica
        info = http.get(f"/sessions/{sid}").json()
        assert info["state"] == "running", info
        # the tracker the gateway placed the session on names the robot it serves, the other none
        serving = [r for r in query_health(stack["bus"], "tracker", timeout=2.0)["replicas"] if r["robots"]]
        assert [(r["replica"], r["robots"]) for r in serving] == [(info["tracker"], [info["robot_id"]])], serving
        assert serving[0]["pid"] == stack["system"].group.pid(tracker_child(info["tracker"]))
        stopped = http.delete(f"/sessions/{sid}")
        assert stopped.status_code == 200, stopped.text
        info = wait_until(lambda: (i := http.get(f"/sessions/{sid}").json())["state"] not in ("running", "starting")
                          and i, 60, "the session's end")
    assert info["state"] == "stopped" and info["frames"] > 60, info
    after = detector_jobs(stack)
    total = {r: after["answered"].get(r, 0) - before["answered"].get(r, 0) for r in replicas}
    assert after["lost"] == before["lost"], after  # no keyframe job went unanswered
    assert sum(total.values()) > sum(split[r] - before["answered"].get(r, 0) for r in replicas), \
        "keyframe jobs stopped with the killed replica"
    # the killed replica comes back (its supervisor restarts it) as the same replica, and is used again
    wait_until(lambda: sorted(detector_jobs(stack)["alive"]) == replicas, 60, "the killed replica's return")
    health = subprocess.run([str(TWOHR), "health", "detector", "--router", stack["router"]], capture_output=True,
                            text=True, timeout=60, env=os.environ | stack["system"].access.env("client")
                            | {"TWOHR_ZENOH_USER": "client"})
    lines = [line for line in health.stdout.splitlines() if line.startswith("detector")]
    assert health.returncode == 0 and len(lines) == 2, health.stdout + health.stderr
    pids = [stack["system"].group.pid(name) for name in ("detector", "detector-2")]
    assert sorted(int(line.split(" pid ")[1].split(":")[0]) for line in lines) == sorted(pids), (lines, pids)
    assert all(f" on {os.uname().nodename} pid " in line for line in lines), lines


def test_two_robots_at_once_each_get_a_tracker_of_their_own(stack, dev_sequence, camera_hz):
    frames = 60
    before = {r["replica"]: r["received"] for r in replica_health_of(stack, "tracker")}
    with httpx.Client(base_url=stack["url"], timeout=30) as http:
        sessions = {}
        for robot, start in (("left", 0), ("right", 400)):
            created = http.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": robot,
                                                   "rate": camera_hz / RECORDED_HZ,
                                                   "start": start, "max_frames": frames, "record": False,
                                                   "config": FAST})
            assert created.status_code == 201, created.text
            sessions[robot] = created.json()
        placed = {robot: info["tracker"] for robot, info in sessions.items()}
        assert sorted(placed.values()) == sorted(before) and len(set(placed.values())) == 2, (placed, before)

        def both_served():
            serving = {r["replica"]: r["robots"] for r in replica_health_of(stack, "tracker")}
            return serving if all(serving.get(placed[robot]) == [robot] for robot in placed) else None

        wait_until(both_served, 60, "each tracker serving its robot")
        done = {robot: wait_until(lambda s=info["id"]: (i := http.get(f"/sessions/{s}").json())["state"]
                                  not in ("running", "starting") and i, 120, f"{robot}'s session to end")
                for robot, info in sessions.items()}
    for info in done.values():
        assert info["state"] == "finished" and info["frames"] >= frames // 2, info
    # only its own tracker takes in a robot's frames: each received its robot's (and the controls of both
    # sessions), none of the other's (64 and 64 here; 124 each if both took every frame)
    after = {r["replica"]: r["received"] for r in replica_health_of(stack, "tracker")}
    received = {replica: after[replica] - before[replica] for replica in before}
    for robot, replica in placed.items():
        assert done[robot]["frames"] <= received[replica] < frames + frames // 2, (received, done)


def test_a_tracker_that_dies_hands_its_robot_to_another_in_the_same_map(stack, dev_sequence, camera_hz):
    """SIGKILL of the tracker serving a robot mid-session: within 2 s the gateway moves the session to the other
    tracker, which goes on in the latest snapshot of the robot's map; the session stays running, poses go on, and
    the whole run, before and after the move, scores within 0.03 m under one alignment (a new frame would not)."""
    with httpx.Client(base_url=stack["url"], timeout=30) as http:
        sessions = {}
        for robot, start, frames in (("moved", 0, 330), ("spared", 280, 150)):
            created = http.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": robot,
                                                   "rate": camera_hz / RECORDED_HZ,
                                                   "start": start, "max_frames": frames, "record": False,
                                                   "config": FAST})
            assert created.status_code == 201, created.text
            sessions[robot] = created.json()
        moved_id, doomed = sessions["moved"]["id"], sessions["moved"]["tracker"]
        assert doomed and doomed != sessions["spared"]["tracker"], sessions
        wait_until(lambda: http.get(f"/sessions/{moved_id}").json()["frames"] >= 120, 60, "120 poses before the kill")
        pid = next(t["pid"] for t in http.get("/healthz").json()["trackers"] if t["replica"] == doomed)
        assert pid == stack["system"].group.pid(tracker_child(doomed))
        os.kill(pid, signal.SIGKILL)
        killed_at = time.monotonic()
        info = wait_until(lambda: (i := http.get(f"/sessions/{moved_id}").json())["tracker"] != doomed and i, 10,
                          "the session's move")
        moved_after = time.monotonic() - killed_at
        assert info["state"] == "running" and info["moves"] == 1, info
        assert info["tracker"] == sessions["spared"]["tracker"], info
        posed_at_move = info["frames"]
        done = {robot: wait_until(lambda s=s["id"]: (i := http.get(f"/sessions/{s}").json())["state"]
                                  not in ("running", "starting") and i, 120, f"{robot}'s session to end")
                for robot, s in sessions.items()}
        served = http.get(f"/sessions/{moved_id}/trajectory")  # waits for the refined trajectory
        moved, spared = http.get(f"/sessions/{moved_id}").json(), done["spared"]
    print(f"moved in {moved_after:.2f} s; {posed_at_move} poses then, {moved['frames']} at the end; "
          f"ATE {moved['ate_rmse']} m ({moved['trajectory']}), online {moved['ate_rmse_online']} m")
    assert moved_after <= 2.0, moved_after
    assert moved["state"] == "finished" and moved["frames"] >= posed_at_move + 30, moved  # a second's frames at least
    assert served.headers["x-twohr-trajectory"] == "refined", served.headers
    assert len(served.text.splitlines()) >= moved["frames"] - 10, "the refined trajectory lacks the early frames"
    assert moved["ate_rmse"] <= 0.03, moved
    assert spared["state"] == "finished" and spared["frames"] >= 75, spared
    # the killed tracker comes back (its supervisor restarts it), for the tests after this one
    wait_until(lambda: len(replica_health_of(stack, "tracker")) == 2, 60, "the killed tracker's return")


def replica_health_of(stack, service: str) -> list[dict]:
    return query_health(stack["bus"], service, timeout=2.0)["replicas"]


@pytest.mark.parametrize("argv, message", [
    (["up", "--replicas", "detector=0"], "detector=0: a service needs at least one replica"),
    (["up", "--replicas", "planner=2"], "replicas of 'planner': planner is no service"),
    (["up", "--replicas", "tracker=0"], "tracker=0: a service needs at least one replica"),
    (["up", "--join", "tcp/127.0.0.1:9", "--only", "tracker", "--insecure"],
     "a robot tracks itself with twohr camera --edge"),
    (["up", "--replicas", "detector"], "write SERVICE=COUNT"),
    (["up", "--join", "tcp/127.0.0.1:9"], "--join needs --only"),
    (["up", "--join", "tcp/127.0.0.1:9", "--only", "detector"], "give the fleet's keys"),
    (["up", "--only", "detector"], "--only names the services a --join host runs"),
])
def test_bad_replica_options_are_one_clear_line(argv, message):
    result = subprocess.run([str(TWOHR), *argv], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
