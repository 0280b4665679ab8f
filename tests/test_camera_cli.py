"""`twohr camera`: a recorded sequence replayed at camera rate onto a real router, and the missing-camera error."""

import json
import subprocess
import sys
import threading
import time

from twohr import keys
from twohr.bus import open_session
from twohr.dataset import CAMERA_PRESETS, RGBDSequence
from twohr.messages import FrameMsg, decode
from twohr_app.cli import main


def test_replay_publishes_frames_with_intrinsics(bus_config, zenoh_router, dev_sequence, tmp_path):
    config = tmp_path / "client.json5"
    config.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [zenoh_router]},
                                  "scouting": {"multicast": {"enabled": False}}}))
    client = open_session(bus_config)
    received = []
    subscriber = client.declare_subscriber(keys.key("live1", keys.RAW_CAMERA), lambda s: received.append(
        decode(s.payload.to_bytes(), FrameMsg, only=("depth",))))
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("rc", main(
        ["camera", "--replay", str(dev_sequence), "--rate", "30", "--robot", "live1", "--frames", "12",
         "--start", "5", "--zenoh-config", str(config)])))
    runner.start()
    runner.join(timeout=60)
    deadline = time.monotonic() + 5
    while len(received) < 12 and time.monotonic() < deadline:
        time.sleep(0.05)
    subscriber.undeclare()
    client.close()
    assert result["rc"] == 0
    sequence = RGBDSequence(dev_sequence)
    assert [m.frame_index for m, _ in received] == list(range(5, 17))
    assert [m.stamp for m, _ in received] == [sequence.records[i].stamp for i in range(5, 17)]
    bonn = CAMERA_PRESETS["bonn"]
    for message, arrays in received:
        assert message.robot_id == "live1" and message.session_id == "live"
        assert (message.camera.fx, message.camera.cy, message.camera.depth_factor) == (bonn.fx, bonn.cy, 5000.0)
        assert arrays["depth"].shape == (bonn.height, bonn.width)


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True,
                          timeout=60)


def test_realsense_without_library_or_camera_is_one_line_and_exit_2():
    proc = run_cli("camera", "--realsense", "--robot", "r1")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and ("pyrealsense2" in lines[0] or "no RealSense camera" in lines[0])


def test_bad_inputs_exit_2(tmp_path, dev_sequence):
    missing = run_cli("camera", "--replay", str(tmp_path / "nope"))
    assert missing.returncode == 2 and "sequence folder not found" in missing.stderr
    bad_config = tmp_path / "bad.json5"
    bad_config.write_text("{ mode: ")
    proc = run_cli("camera", "--replay", str(dev_sequence), "--zenoh-config", str(bad_config))
    assert proc.returncode == 2 and "invalid Zenoh config" in proc.stderr
    robot = run_cli("camera", "--replay", str(dev_sequence), "--robot", "bad robot")
    assert robot.returncode == 2 and "invalid robot id" in robot.stderr
