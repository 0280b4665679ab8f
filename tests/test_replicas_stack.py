"""Replicas in a running stack: ``twohr up --replicas detector=2`` shares the keyframe jobs of a live session between
two detector processes; one killed with SIGKILL mid-session loses no job (the one in flight goes to the other) and
comes back as the same replica once its supervisor restarts it; ``twohr health`` lists both with their host.
Bad ``--replicas`` and ``--join`` input is one clear line each."""

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
TWOHR = Path(sys.executable).with_name("twohr")


@pytest.fixture(scope="module")
def stack(tmp_path_factory, dev_sequence):
    router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    system = start_system(router, [str(dev_sequence.parent)], str(tmp_path_factory.mktemp("recordings")),
                          "127.0.0.1", port, timeout=180, replicas={"detector": 2})
    session = open_session(system.bus("gateway"))
    yield {"system": system, "url": f"http://127.0.0.1:{port}", "router": router, "bus": session}
    session.close()
    system.stop()


def detector_jobs(stack) -> dict:
    return query_health(stack["bus"], "tracker", timeout=2.0)["jobs"]["detector"]


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
    assert all(f" on {os.uname().nodename}: " in line for line in lines), lines


@pytest.mark.parametrize("argv, message", [
    (["up", "--replicas", "detector=0"], "detector=0: a service needs at least one replica"),
    (["up", "--replicas", "planner=2"], "replicas of 'planner': planner is no service"),
    (["up", "--replicas", "tracker=2"], "tracker keeps every session's map in one process"),
    (["up", "--replicas", "detector"], "write SERVICE=COUNT"),
    (["up", "--join", "tcp/127.0.0.1:9"], "--join needs --only"),
    (["up", "--join", "tcp/127.0.0.1:9", "--only", "detector"], "give the fleet's keys"),
    (["up", "--only", "detector"], "--only names the services a --join host runs"),
])
def test_bad_replica_options_are_one_clear_line(argv, message):
    result = subprocess.run([str(TWOHR), *argv], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
