"""`twohr run --view`: the in-process pipeline streams to a Foxglove WebSocket client while it runs."""

import subprocess
import sys
import time

from twohr.bus import free_port


def test_twohr_run_view_streams_every_channel(dev_sequence, tmp_path, foxglove_listener):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "twohr_services.cli", "run", "--sequence", str(dev_sequence),
                             "--out", str(tmp_path / "run"), "--frames", "90", "--quiet", "--view", "--view-port",
                             str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("live view: https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://127.0.0.1:"
                               f"{port}"), line + proc.stderr.read()
        client = foxglove_listener(f"ws://127.0.0.1:{port}")  # before the models are loaded: no frame is missed
        out, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err
    finally:
        proc.kill()
    time.sleep(0.2)
    counts = client.counts
    assert set(client.topics()) == {"/run/camera/image", "/run/camera/calibration", "/run/camera/keypoints",
                                    "/run/camera/dynamic_mask", "/run/pose", "/run/path", "/run/map", "/tf"}
    for topic in ("/run/camera/image", "/run/camera/calibration", "/run/pose", "/tf"):
        assert counts.get(topic) == 90, (topic, counts)
    assert counts["/run/path"] == 18 and 1 <= counts["/run/map"] < 90, counts
    assert counts["/run/camera/keypoints"] >= 80 and counts["/run/camera/dynamic_mask"] >= 60, counts
    assert len(client.decode("/run/path").poses) == 86  # sent with every 5th pose
    cloud = client.decode("/run/map")
    assert len(cloud.data) // cloud.point_stride > 100
    assert "ATE RMSE" in out
