"""The Foxglove live view on real frames: a WebSocket client speaking Foxglove's protocol sees every channel."""

import socket
import time

import numpy as np
import pytest

from twohr.bus import free_port
from twohr.dataset import RGBDSequence
from twohr.errors import TwohrError
from twohr.foxglove_live import LiveView


def wait_for(condition, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_live_view_advertises_and_streams_every_channel(dev_sequence, foxglove_listener):
    seq = RGBDSequence(dev_sequence)
    view = LiveView(port=free_port(), jpeg_quality=80)
    try:
        frames = list(seq.frames(0, 6))
        convert = view.converter
        # the first frame advertises the channels; the client subscribes to them
        first = frames[0]
        view.log(convert.frame("r1", first.stamp, seq.camera, rgb=first.rgb))
        view.log(convert.pose("r1", first.stamp, [0, 0, 0], [0, 0, 0, 1]))
        view.log(convert.landmarks("r1", first.stamp, np.zeros((5, 3))))
        view.log(convert.keypoints("r1", first.stamp, np.array([[10.0, 20.0]])))
        client = foxglove_listener(f"ws://127.0.0.1:{view.port}")  # the protocol's name in its spec
        sdk_client = foxglove_listener(f"ws://127.0.0.1:{view.port}", "foxglove.sdk.v1")  # its name in the SDK
        wait_for(lambda: len(client.subscriptions) == 7 and len(sdk_client.subscriptions) == 7)
        assert client.topics() == {
            "/r1/camera/image": "foxglove.CompressedImage", "/r1/camera/calibration": "foxglove.CameraCalibration",
            "/r1/pose": "foxglove.PoseInFrame", "/tf": "foxglove.FrameTransforms", "/r1/path": "foxglove.PosesInFrame",
            "/r1/map": "foxglove.PointCloud", "/r1/camera/keypoints": "foxglove.ImageAnnotations"}
        time.sleep(0.5)  # the subscriptions reach the server
        for i, frame in enumerate(frames[1:], start=1):
            view.log(convert.frame("r1", frame.stamp, seq.camera, rgb=frame.rgb))
            view.log(convert.pose("r1", frame.stamp, [0.1 * i, 0, 0], [0, 0, 0, 1]))
            view.log(convert.landmarks("r1", frame.stamp, np.ones((10 * i, 3))))
        wait_for(lambda: client.counts.get("/r1/map", 0) == 5)
        assert client.counts["/r1/camera/image"] == 5 and client.counts["/r1/camera/calibration"] == 5
        assert client.counts["/r1/pose"] == 5 and client.counts["/tf"] == 5
        wait_for(lambda: sdk_client.counts.get("/r1/map", 0) == 5)
        assert sdk_client.counts == client.counts
        image = client.decode("/r1/camera/image")
        assert image.format == "jpeg" and image.data[:2] == b"\xff\xd8"
        assert client.decode("/r1/pose").pose.position.x == pytest.approx(0.5)
        cloud = client.decode("/r1/map")
        assert len(cloud.data) // cloud.point_stride == 50
        assert client.decode("/r1/camera/calibration").K[0] == pytest.approx(seq.camera.fx)
    finally:
        view.close()


def test_a_taken_port_is_one_clear_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(TwohrError, match=f"live view: cannot listen on 127.0.0.1:{port}"):
            LiveView(port=port)
