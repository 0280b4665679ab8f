"""Two live robots at 30 Hz on one stack that carries two (``--max-robots 2``): each its own ``twohr camera
--replay`` at 30 Hz on its own stretch of the dev frames (0-299 and 260-559), as a new user would try. Both sessions
finish with fair shares (posed fractions within 10 points) and usable maps (ATE of each served trajectory at most
0.03 m); a third robot asking while they run gets 503 with ``Retry-After``."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest

from twohr.bus import free_port
from twohr.dataset import RGBDSequence
from twohr_app.supervisor import start_system
from twohr_lab.live import _stack, camera_session

FRAMES = 300


@pytest.fixture(scope="module")
def two_robot_stack(tmp_path_factory, dev_sequence):
    scratch = tmp_path_factory.mktemp("capacity")
    router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    system = start_system(router, [str(dev_sequence.parent)], str(scratch / "recordings"), "127.0.0.1", port,
                          timeout=180, max_robots=2)
    yield {"system": system, "scratch": scratch, "router": router, "port": port}
    system.stop()


def test_two_robots_at_camera_rate_share_fairly_and_a_third_is_turned_away(two_robot_stack, dev_sequence):
    sequence = RGBDSequence(dev_sequence)
    s = two_robot_stack
    robots = {"r1": 0, "r2": len(sequence) - FRAMES}
    stacks = {robot: _stack(s["system"], Path(s["scratch"]), s["router"], s["port"], robot, None) for robot in robots}
    rows: dict[str, dict] = {}

    def run(robot: str) -> None:
        rows[robot] = camera_session(stacks[robot], sequence, robot, FRAMES, busy=0, progress=False,
                                     start=robots[robot])

    threads = [threading.Thread(target=run, args=(robot,)) for robot in robots]
    for thread in threads:
        thread.start()
    url = f"http://127.0.0.1:{s['port']}"
    deadline = time.monotonic() + 60
    while sum(x["state"] in ("starting", "running") for x in httpx.get(f"{url}/sessions", timeout=30).json()) < 2:
        assert time.monotonic() < deadline, "the two sessions did not start"
        time.sleep(0.2)
    third = httpx.post(f"{url}/sessions", json={"source": "camera", "robot_id": "r3"}, timeout=30)
    assert third.status_code == 503 and int(third.headers["retry-after"]) > 0, third.text
    assert "the stack is full" in third.json()["detail"]
    for thread in threads:
        thread.join(300)
    posed = {robot: row["posed_percent"] for robot, row in rows.items()}
    ate = {robot: row["ate_served"] for robot, row in rows.items()}
    print(f"two robots at 30 Hz: posed % {posed}, ATE served {ate}, online "
          f"{ {r: row['ate_online'] for r, row in rows.items()} }, latency p50/p99 "
          f"{ {r: (row['latency_ms_p50'], row['latency_ms_p99']) for r, row in rows.items()} }")
    assert abs(posed["r1"] - posed["r2"]) <= 10, posed
    assert all(value is not None and value <= 0.03 for value in ate.values()), ate
