"""A live robot end to end, as issue 17's check runs it: `twohr up --ros2-domain 0` (here `start_system`), a camera
session started over HTTP, `twohr camera --replay ... --rate 30` publishing with the client config that `twohr up`
writes, a plain Zenoh client from the same config receiving the poses as ROS 2 PoseStamped samples on rmw_zenoh
keys, decoded by rosbags, then DELETE and the trajectory download, scored against the ground truth."""

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from twohr.bus import BusConfig, free_port, open_session
from twohr.dataset import RGBDSequence
from twohr.evaluation import evaluate
from twohr.service import PER_FRAME_NICE
from twohr.trajectory import read_tum
from twohr_app.fleet import write_client_config
from twohr_app.supervisor import start_system

FRAMES = 150
POSE_TYPE = "geometry_msgs::msg::dds_::PoseStamped_"


@pytest.fixture(scope="module")
def live_stack(tmp_path_factory, dev_sequence):
    recordings = tmp_path_factory.mktemp("live_recordings")
    router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    system = start_system(router, [str(dev_sequence.parent)], str(recordings), "127.0.0.1", port, timeout=180,
                          ros2_domain=0)
    client_config = write_client_config(tmp_path_factory.mktemp("client") / "C.json5", router, system.credentials)
    yield {"system": system, "url": f"http://127.0.0.1:{port}", "client_config": client_config}
    system.stop()


def play_camera(client: httpx.Client, live_stack: dict, dev_sequence, robot: str, session_id: str,
                frames: int, rate: float = 30.0) -> dict:
    """`twohr camera --replay` at ``rate`` Hz into a running camera session; returns the session's state once the
    last frames' poses are in."""
    camera = subprocess.run(
        [sys.executable, "-m", "twohr_app", "camera", "--replay", str(dev_sequence), "--rate", f"{rate:g}",
         "--robot", robot, "--zenoh-config", str(live_stack["client_config"]), "--frames", str(frames)],
        capture_output=True, text=True, timeout=300)
    assert camera.returncode == 0, camera.stderr
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        info = client.get(f"/sessions/{session_id}").json()
        if info["frames_sent"] == frames and info["frames"] + info["frames_dropped"] >= frames:
            break
        time.sleep(0.5)
    return info


def test_camera_session_over_ros2_end_to_end(live_stack, dev_sequence, tmp_path, camera_hz):
    typestore = get_typestore(Stores.ROS2_JAZZY)
    samples: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample) -> None:
        with lock:
            samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    observer = open_session(BusConfig(config_file=live_stack["client_config"]))
    sub = observer.declare_subscriber("0/**", on_sample)
    try:
        with httpx.Client(base_url=live_stack["url"], timeout=30) as client:
            response = client.post("/sessions", json={"source": "camera", "robot_id": "live1"})
            assert response.status_code == 201, response.text
            session_id = response.json()["id"]
            assert client.post("/sessions", json={"source": "camera", "robot_id": "live1",
                                                  "sequence": "x"}).status_code == 422
            info = play_camera(client, live_stack, dev_sequence, "live1", session_id, FRAMES, camera_hz)
            assert info["state"] == "running" and info["source"] == "camera", info
            time.sleep(1.0)
            info = client.delete(f"/sessions/{session_id}").json()
            assert info["state"] == "stopped"
            (tmp_path / "live.txt").write_text(client.get(f"/sessions/{session_id}/trajectory").text)
    finally:
        sub.undeclare()
        observer.close()

    poses = [(k, d) for k, d in samples if f"/{POSE_TYPE}/RIHS01_" in k]
    assert poses and all(k.startswith("0/live1/pose/") for k, _ in poses), sorted({k for k, _ in samples})[:5]
    decoded = [typestore.deserialize_cdr(d, "geometry_msgs/msg/PoseStamped") for _, d in poses]
    trajectory = read_tum(tmp_path / "live.txt")
    print(f"live: {len(decoded)} PoseStamped, {len(trajectory)} poses served, session {info}")
    # every pose the tracker made reached ROS 2, decodable by an independent CDR implementation
    assert len(decoded) == len(trajectory) == info["frames"]
    # every frame relayed is accounted for: posed, or dropped as stale (throughput is the bench's business)
    assert info["frames"] + info["frames_dropped"] == FRAMES and info["frames"] >= 10, info
    stamps = sorted(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in decoded)
    assert abs(stamps[-1] - trajectory.stamps.max()) < 1e-6
    sequence = RGBDSequence(dev_sequence)
    report, _ = evaluate(sequence.ground_truth(sequence.default_gt_extrinsic()), trajectory)
    print(f"live: {info['frames']} poses of {FRAMES} frames ({info['frames_dropped']} dropped), "
          f"{len(decoded)} PoseStamped decoded, ATE {report.ate.rmse:.4f} m")
    assert report.ate.rmse < 0.05


def thread_niceness(pid: int) -> list[int]:
    """The niceness of every thread of a process."""
    values = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            values.append(os.getpriority(os.PRIO_PROCESS, int(task.name)))
        except (OSError, ValueError):  # the thread has ended
            continue
    return values


def test_a_busy_process_beside_the_stack_does_not_starve_the_map(live_stack, dev_sequence, tmp_path):
    """A robot's CPU is never idle. With one busy process at normal priority beside the stack, no thread of the map's
    work runs below it: the tracker above it where the OS allows, the keyframe stages (detector, yolo, matcher) level
    with it, only the recorder below. With the keyframe stages at niceness 10, issue 29 measured served trajectories
    0.117 and 0.143 m off; this fails on that. The session goes on beside the busy process: every frame is posed or
    counted as dropped, and the served trajectory is the refined one, a finite pose for each posed frame.

    How close that trajectory stays to the ground truth under load depends on the machine and on whatever else runs
    (the suite itself, here), so it is a benchmark: `twohr bench --live --busy 0,1,2` (targets: one busy process at
    most 0.025 m, two at most 0.03 m; see the issue notes for the figures)."""
    frames = 2 * FRAMES
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        niceness = {child.name: thread_niceness(child.proc.pid) for child in live_stack["system"].group.children}
        busy_niceness = os.getpriority(os.PRIO_PROCESS, busy.pid)
        with httpx.Client(base_url=live_stack["url"], timeout=60) as client:
            session_id = client.post("/sessions", json={"source": "camera", "robot_id": "busy1",
                                                        "record": False}).json()["id"]
            info = play_camera(client, live_stack, dev_sequence, "busy1", session_id, frames)
            client.delete(f"/sessions/{session_id}")
            served = client.get(f"/sessions/{session_id}/trajectory")
    finally:
        busy.kill()
    assert busy_niceness == 0
    tracker_nice = PER_FRAME_NICE if os.geteuid() == 0 else 0  # raising a priority needs root or CAP_SYS_NICE
    assert set(niceness["tracker"]) == {tracker_nice}, niceness["tracker"]
    for name in ("source", "detector", "yolo", "matcher", "gateway", "ros2"):
        assert max(niceness[name]) <= busy_niceness, (name, niceness[name])
    assert min(niceness["recorder"]) >= busy_niceness, niceness["recorder"]
    assert info["frames"] + info["frames_dropped"] == frames, info
    assert served.headers["x-twohr-trajectory"] == "refined"
    (tmp_path / "busy.txt").write_text(served.text)
    trajectory = read_tum(tmp_path / "busy.txt")
    assert info["frames"] <= len(trajectory) <= frames and np.isfinite(trajectory.poses).all()
    sequence = RGBDSequence(dev_sequence)
    report, _ = evaluate(sequence.ground_truth(sequence.default_gt_extrinsic()), trajectory)
    print(f"busy: {info['frames']} poses of {frames} frames, health {info['health']} ({info['health_detail']}), "
          f"ATE {report.ate.rmse:.4f} m (a benchmark figure here, not a bound)")
