"""`twohr run --view`: the in-process pipeline streams to a Foxglove WebSocket client while it runs."""

import csv
import json
import subprocess
import sys


def test_twohr_run_view_streams_every_channel(viewed_run):
    """The run of :func:`viewed_run` (``tests/conftest.py``: 90 frames, the client subscribed before the models load;
    test_run_report.py reads the report the same run writes)."""
    line, port = viewed_run["first_line"], viewed_run["port"]
    assert line.startswith("live view: https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://127.0.0.1:"
                           f"{port}"), line + viewed_run["stderr"]
    assert viewed_run["returncode"] == 0, viewed_run["stderr"]
    client, out = viewed_run["client"], viewed_run["stdout"]
    counts = client.counts
    assert set(client.topics()) == {"/run/camera/image", "/run/camera/calibration", "/run/camera/keypoints",
                                    "/run/camera/dynamic_mask", "/run/pose", "/run/path", "/run/keyframes",
                                    "/run/path_refined", "/run/map", "/tf"}
    for topic in ("/run/camera/image", "/run/camera/calibration", "/run/pose", "/tf"):
        assert counts.get(topic) == 90, (topic, counts)
    assert counts["/run/path"] == 18 and 1 <= counts["/run/map"] < 90, counts
    assert counts["/run/camera/keypoints"] >= 80, counts
    # a mask with every frame tracked with one: how many depends on how soon YOLO's first answer came (the load)
    with open(viewed_run["out"] / "stats.csv", newline="") as fh:
        masked = sum(int(row["mask_age"]) >= 0 for row in csv.DictReader(fh))
    assert 1 <= masked and counts["/run/camera/dynamic_mask"] == masked, (masked, counts)
    assert len(client.decode("/run/path").poses) == 86  # sent with every 5th pose
    cloud = client.decode("/run/map")
    assert len(cloud.data) // cloud.point_stride > 100
    assert "ATE RMSE" in out


def test_bench_view_measures_the_live_view_against_the_same_run(dev_sequence, tmp_path):
    out = tmp_path / "bench"
    result = subprocess.run([sys.executable, "-m", "twohr_app", "bench", "--view", "--sequence",
                             str(dev_sequence), "--frames", "20", "--runs", "1", "--quiet", "--out", str(out)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "bench.json").read_text())["view"]
    assert report["frames"] == 20 and report["runs"] == 1
    for label in ("without_view", "with_view"):
        assert len(report["cpu_ms_per_frame"][label]) == 1 and report["cpu_ms_per_frame"][label][0] > 0
    received = report["viewer_received_per_run"][0]  # the viewer got every frame's image and pose
    assert received["/run/camera/image"] == 20 and received["/run/pose"] == 20 and received["/run/map"] >= 1
    assert "ms/frame with it and a viewer subscribed" in result.stdout
