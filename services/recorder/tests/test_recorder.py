"""The recorder on real frames and a real Zenoh router: counts, read-back, survival of a kill."""

import os
import signal
import subprocess
import sys
import threading
import time

from mcap.reader import make_reader

from twohr import keys
from twohr.bus import open_session, wait_for_services
from twohr.dataset import RGBDSequence
from twohr.messages import ControlMsg, PoseMsg, decode, encode
from twohr.service import declare_publisher
from twohr_services.recorder.core import SessionRecorder, read_messages, topic_counts
from twohr_services.recorder.service import RecorderService
from twohr_services.source.core import frame_payloads


def pose(i, stamp, session="sess1", robot="r1"):
    return encode(PoseMsg(session_id=session, robot_id=robot, frame_index=i, stamp=stamp, position=[0.1 * i, 0, 0],
                          orientation=[0, 0, 0, 1], status="tracking"))


def test_session_file_has_every_stream_and_foxglove_channels(dev_sequence, tmp_path):
    seq = RGBDSequence(dev_sequence)
    rec = SessionRecorder(tmp_path / "s.mcap")
    n = 0
    for item in frame_payloads(seq, "sess1", "r1", max_frames=5):
        rec.write("twohr/r1/frames", item.payload)
        rec.write("twohr/r1/pose", pose(item.index, item.stamp))
        n += 1
    rec.close()
    with open(tmp_path / "s.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
    counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
    assert counts == {"/twohr/r1/frames": n, "/r1/camera/rgb": n, "/r1/camera/depth": n, "/twohr/r1/pose": n,
                      "/r1/pose": n, "/tf": n}
    schemas = {s.name for s in summary.schemas.values()}
    assert {"foxglove.CompressedImage", "foxglove.PoseInFrame", "foxglove.FrameTransform", "twohr.Frame"} <= schemas
    frames = [d for t, d, _ in read_messages(tmp_path / "s.mcap") if t == "/twohr/r1/frames"]
    msg, arrays = decode(frames[2])
    assert msg.frame_index == 2 and arrays["rgb"].shape == (480, 640, 3)


def test_recorder_service_over_the_bus(bus_config, dev_sequence, tmp_path):
    service = RecorderService(bus_config, tmp_path)
    stop = threading.Event()
    thread = threading.Thread(target=service.run, args=(stop,), daemon=True)
    thread.start()
    client = open_session(bus_config)
    try:
        wait_for_services(client, ["recorder"], timeout=10)
        control, frames, poses = (declare_publisher(client, k) for k in
                                  (keys.key("r1", keys.CONTROL), "twohr/r1/frames", "twohr/r1/pose"))
        start = ControlMsg(session_id="sess2", robot_id="r1", frame_index=-1, stamp=0, command="start")
        control.put(encode(start))
        for item in frame_payloads(RGBDSequence(dev_sequence), "sess2", "r1", max_frames=4):
            frames.put(item.payload)
            poses.put(pose(item.index, item.stamp, "sess2"))
        poses.put(pose(9, 0.0, "other_session"))  # not recorded into sess2
        poses.put(b"malformed")
        deadline = time.time() + 15
        # keys have no ordering between them: stop only once everything else has been handled
        while service.counters.processed + service.counters.malformed < 11:
            assert time.time() < deadline, service.counters
            time.sleep(0.1)
        control.put(encode(start.model_copy(update={"command": "stop"})))
        while "sess2" in service.open:
            assert time.time() < deadline, service.counters
            time.sleep(0.1)
        counts = topic_counts(tmp_path / "sess2.mcap")
        assert counts["/twohr/r1/frames"] == 4 and counts["/twohr/r1/pose"] == 4
        assert counts["/twohr/r1/control"] == 2
        assert service.counters.malformed == 1
    finally:
        stop.set()
        thread.join(5)
        client.close()


def test_chunks_survive_a_kill(bus_config, zenoh_router, dev_sequence, tmp_path):
    env = dict(os.environ, TWOHR_ZENOH_ROUTER=zenoh_router)
    proc = subprocess.Popen([sys.executable, "-m", "twohr_services.recorder", "--recordings", str(tmp_path)], env=env)
    client = open_session(bus_config)
    try:
        wait_for_services(client, ["recorder"], timeout=20)
        control, frames = (declare_publisher(client, k) for k in (keys.key("r1", keys.CONTROL), "twohr/r1/frames"))
        start = ControlMsg(session_id="sess3", robot_id="r1", frame_index=-1, stamp=0, command="start")
        control.put(encode(start))
        for item in frame_payloads(RGBDSequence(dev_sequence), "sess3", "r1", max_frames=12):
            frames.put(item.payload)
        time.sleep(2.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        frames = [d for t, d, _ in read_messages(tmp_path / "sess3.mcap") if t == "/twohr/r1/frames"]
        # each frame is ~0.4 MB and chunks are 256 kB: all but the last chunk's frames are on disk
        assert len(frames) >= 8
        assert [decode(f)[0].frame_index for f in frames] == list(range(len(frames)))
    finally:
        proc.kill()
        client.close()


def test_recorder_refuses_to_start_on_a_folder_it_cannot_write(tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the recordings folder should be")
    result = subprocess.run([sys.executable, "-m", "twohr_services.recorder", "--recordings", str(blocker)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip().startswith(f"recorder: error: cannot create the recordings folder {blocker}")
