"""The recorder on real frames and a real Zenoh router: counts, read-back, survival of a kill."""

import os
import re
import signal
import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from twohr import keys
from twohr.bus import open_session, wait_for_services
from twohr.dataset import RGBDSequence
from twohr.geometry import rot_to_quat
from twohr.messages import (
    ControlMsg,
    DynamicsMsg,
    KeypointsMsg,
    LandmarksMsg,
    PathMsg,
    PoseMsg,
    decode,
    encode,
    path_arrays,
)
from twohr.service import declare_publisher
from twohr.trajectory import Trajectory, write_tum
from twohr_services.recorder.core import (
    RecordingOptions,
    SessionRecorder,
    read_messages,
    recorded_trajectory,
    topic_counts,
)
from twohr_services.recorder.service import RecorderService
from twohr_services.source.core import frame_payloads


def pose(i, stamp, session="sess1", robot="r1"):
    return encode(PoseMsg(session_id=session, robot_id=robot, frame_index=i, stamp=stamp, position=[0.1 * i, 0, 0],
                          orientation=[0, 0, 0, 1], status="tracking"))


def keypoints(i, stamp, count=500, session="sess1", robot="r1"):
    rng = np.random.default_rng(i)
    arrays = {"xy": rng.uniform(0, 400, (count, 2)).astype(np.float32),
              "descriptors": rng.standard_normal((count, 128)).astype(np.float32),
              "scores": rng.uniform(0, 1, count).astype(np.float32)}
    message = KeypointsMsg(session_id=session, robot_id=robot, frame_index=i, stamp=stamp, width=640, height=480)
    return encode(message, arrays)


def dynamics(i, stamp, session="sess1", robot="r1"):
    mask = np.zeros((480, 640), np.uint8)
    mask[100:300, 200:260] = 1  # one person-sized region
    message = DynamicsMsg(session_id=session, robot_id=robot, frame_index=i, stamp=stamp, names=["person"])
    arrays = {"boxes": np.array([[200, 100, 260, 300]], np.float32), "scores": np.array([0.9], np.float32),
              "class_ids": np.array([0], np.int32), "mask": mask}
    return encode(message, arrays, encodings={"mask": "png"})


def landmarks(i, stamp, count=300, session="sess1", robot="r1"):
    points = np.random.default_rng(i).uniform(-2, 2, (count, 3)).astype(np.float32)
    return encode(LandmarksMsg(session_id=session, robot_id=robot, frame_index=i, stamp=stamp), {"points": points})


def record(path, sequence, frames, options=None):
    """A session of ``frames`` real frames with a pose each, keypoints and map points every 5th, a mask every 3rd."""
    rec = SessionRecorder(path, options)
    for item in frame_payloads(sequence, "sess1", "r1", max_frames=frames):
        i, t = item.index, item.stamp
        rec.write("twohr/r1/frames", item.payload)
        rec.write("twohr/r1/pose", pose(i, t))
        if i % 5 == 0:
            rec.write("twohr/r1/keypoints", keypoints(i, t))
            rec.write("twohr/r1/landmarks", landmarks(i, t, count=100 * (i // 5 + 1)))
        if i % 3 == 0:
            rec.write("twohr/r1/dynamics", dynamics(i, t))
    rec.close()
    return path


def test_standard_recording_is_lean_typed_and_readable_by_standard_readers(dev_sequence, tmp_path):
    seq = RGBDSequence(dev_sequence)
    n = 20
    path = record(tmp_path / "s.mcap", seq, n)
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
    assert counts == {"/r1/camera/image": n, "/r1/camera/calibration": n, "/twohr/r1/pose": n, "/r1/pose": n,
                      "/tf": n, "/r1/path": 2, "/twohr/r1/keypoints": 4, "/twohr/r1/landmarks": 4, "/r1/map": 4,
                      "/twohr/r1/dynamics": 7, "/r1/camera/keypoints": 4,
                      "/r1/camera/dynamic_mask": 7}
    schemas = {s.name: s.encoding for s in summary.schemas.values()}
    for name in ("CompressedImage", "CameraCalibration", "PoseInFrame", "PosesInFrame", "PointCloud",
                 "FrameTransforms", "ImageAnnotations"):
        assert schemas[f"foxglove.{name}"] == "protobuf"
    assert "twohr.Frame" not in schemas  # the image is stored once, on the Foxglove channel

    # decoded with the schemas stored in the file (mcap + protobuf), as any MCAP tool does
    decoded: dict[str, list] = {}
    foxglove_topics = [t for t in counts if not t.startswith("/twohr/")]
    with open(path, "rb") as fh:
        for _schema, channel, _message, proto in make_reader(fh, decoder_factories=[DecoderFactory()]
                                                             ).iter_decoded_messages(topics=foxglove_topics):
            decoded.setdefault(channel.topic, []).append(proto)
    image = decoded["/r1/camera/image"][3]
    assert image.format == "jpeg" and image.frame_id == "r1/camera"
    assert cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR).shape == (480, 640, 3)
    assert abs(image.timestamp.seconds + image.timestamp.nanos * 1e-9 - seq.records[3].stamp) < 1e-6
    calib = decoded["/r1/camera/calibration"][0]
    assert list(calib.K) == pytest.approx([seq.camera.fx, 0, seq.camera.cx, 0, seq.camera.fy, seq.camera.cy, 0, 0, 1])
    assert (calib.width, calib.height) == (640, 480)
    assert [p.pose.position.x for p in decoded["/r1/pose"]] == pytest.approx([0.1 * i for i in range(n)])
    assert [len(p.poses) for p in decoded["/r1/path"]] == [1, 11]
    clouds = decoded["/r1/map"]
    assert [len(c.data) // c.point_stride for c in clouds] == [100, 200, 300, 400]
    assert [f.name for f in clouds[0].fields] == ["x", "y", "z"]
    tf = decoded["/tf"][5].transforms[0]
    assert (tf.parent_frame_id, tf.child_frame_id, tf.translation.x) == ("world", "r1/camera", pytest.approx(0.5))
    assert [len(a.points[0].points) for a in decoded["/r1/camera/keypoints"]] == [500] * 4
    mask = decoded["/r1/camera/dynamic_mask"][0]
    assert len(mask.points) == 1  # one region, one outline
    outline = np.array([(p.x, p.y) for p in mask.points[0].points])
    assert outline.min(0) == pytest.approx([200.5, 100.5], abs=1.5) and outline.max(0) == pytest.approx(
        [259.5, 299.5], abs=1.5)

    # descriptors are left out, the rest of the keypoints stays
    kp_payloads = [d for t, d, _ in read_messages(path) if t == "/twohr/r1/keypoints"]
    _, arrays = decode(kp_payloads[0])
    assert arrays["descriptors"].shape == (500, 0) and arrays["xy"].shape == (500, 2)

    # the poses come back for evaluation
    trajectory = recorded_trajectory(path)
    assert len(trajectory) == n and trajectory.positions[:, 0] == pytest.approx([0.1 * i for i in range(n)])

    per_frame = path.stat().st_size / n
    assert per_frame <= 100_000, per_frame


def test_descriptors_and_raw_frames_on_request(dev_sequence, tmp_path):
    seq = RGBDSequence(dev_sequence)
    lean = record(tmp_path / "lean.mcap", seq, 10)
    full = record(tmp_path / "full.mcap", seq, 10, RecordingOptions(record_descriptors=True, record_frames=True))
    counts = topic_counts(full)
    assert counts["/twohr/r1/frames"] == 10 and counts["/r1/camera/image"] == 10
    frames = [d for t, d, _ in read_messages(full) if t == "/twohr/r1/frames"]
    msg, arrays = decode(frames[2])
    assert msg.frame_index == 2 and arrays["rgb"].shape == (480, 640, 3) and arrays["depth"].dtype == np.uint16
    _, arrays = decode(next(d for t, d, _ in read_messages(full) if t == "/twohr/r1/keypoints"))
    assert arrays["descriptors"].shape == (500, 128)
    assert full.stat().st_size > 3 * lean.stat().st_size


def test_twohr_eval_scores_a_recording(dev_sequence, tmp_path):
    seq = RGBDSequence(dev_sequence)
    rec = SessionRecorder(tmp_path / "gt.mcap")
    gt = seq.ground_truth(seq.default_gt_extrinsic())
    for i in range(0, 200, 2):  # the ground-truth poses themselves, as a tracker would publish them
        position, quaternion = gt.poses[i][:3, 3], rot_to_quat(gt.poses[i][:3, :3])
        rec.write("twohr/r1/pose", encode(PoseMsg(session_id="s", robot_id="r1", frame_index=i, stamp=gt.stamps[i],
                                                  position=position.tolist(), orientation=quaternion.tolist(),
                                                  status="tracking")))
    rec.close()
    gt_file = tmp_path / "gt.txt"
    write_tum(gt_file, gt)
    result = subprocess.run([sys.executable, "-m", "twohr_app", "eval", "--gt", str(gt_file), "--est",
                             str(tmp_path / "gt.mcap")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    rmse = float(re.search(r"RMSE ([0-9.e-]+) m", result.stdout).group(1))
    assert rmse < 1e-6 and "paired 100 of 100" in result.stdout, result.stdout
    empty = SessionRecorder(tmp_path / "empty.mcap")
    empty.close()
    result = subprocess.run([sys.executable, "-m", "twohr_app", "eval", "--gt", str(gt_file), "--est",
                             str(tmp_path / "empty.mcap")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "poses of exactly one robot" in result.stderr


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
        deadline = time.time() + 15
        while "sess2" not in service.open:  # keys have no ordering between them: frames only once the file is open
            assert time.time() < deadline, service.counters
            time.sleep(0.05)
        for item in frame_payloads(RGBDSequence(dev_sequence), "sess2", "r1", max_frames=4):
            frames.put(item.payload)
            poses.put(pose(item.index, item.stamp, "sess2"))
        poses.put(pose(9, 0.0, "other_session"))  # not recorded into sess2
        poses.put(b"malformed")
        # robot r2 on its own key, speaking for r1's session (whose id every robot can read): refused
        declare_publisher(client, "twohr/r2/pose").put(pose(8, 0.0, "sess2", robot="r2"))
        deadline = time.time() + 15
        # keys have no ordering between them: stop only once everything else has been handled
        while service.counters.processed + service.counters.malformed < 12:
            assert time.time() < deadline, service.counters
            time.sleep(0.1)
        control.put(encode(start.model_copy(update={"command": "stop"})))
        time.sleep(2 * service.grace)
        assert "sess2" in service.open  # a session with poses: the tracker's refined path is waited for
        refined = Trajectory(np.array([0.0, 0.1]), np.stack([np.eye(4), np.eye(4)]))
        path = PathMsg(session_id="sess2", robot_id="r1", frame_index=3, stamp=0.1, final=True)
        declare_publisher(client, "twohr/r1/path").put(encode(path, path_arrays(refined)))
        while "sess2" in service.open:
            assert time.time() < deadline, service.counters
            time.sleep(0.1)
        counts = topic_counts(tmp_path / "sess2.mcap")
        assert counts.get("/r1/camera/image") == 4 and counts.get("/twohr/r1/pose") == 4, (counts, service.counters)
        assert "/twohr/r1/frames" not in counts
        assert counts["/twohr/r1/control"] == 2 and counts["/twohr/r1/path"] == 1 and counts["/r1/path_refined"] == 1
        np.testing.assert_allclose(recorded_trajectory(tmp_path / "sess2.mcap").poses, refined.poses)
        assert len(recorded_trajectory(tmp_path / "sess2.mcap", online=True)) == 4
        assert service.counters.malformed == 2 and service.refused == {"r1": 1, "r2": 1}, service.refused
    finally:
        stop.set()
        thread.join(5)
        client.close()


def test_chunks_survive_a_kill(bus_config, zenoh_router, dev_sequence, tmp_path):
    env = dict(os.environ, TWOHR_ZENOH_ROUTER=zenoh_router)
    proc = subprocess.Popen([sys.executable, "-m", "twohr_services.recorder", "--recordings", str(tmp_path),
                             "--record-frames"], env=env)
    client = open_session(bus_config)
    try:
        wait_for_services(client, ["recorder"], timeout=20)
        control, frames = (declare_publisher(client, k) for k in (keys.key("r1", keys.CONTROL), "twohr/r1/frames"))
        start = ControlMsg(session_id="sess3", robot_id="r1", frame_index=-1, stamp=0, command="start")
        control.put(encode(start))
        deadline = time.monotonic() + 20
        while not (tmp_path / "sess3.mcap").is_file():  # keys have no ordering between them: frames once it is open
            assert time.monotonic() < deadline, "the recorder did not open the session's file"
            time.sleep(0.05)
        for item in frame_payloads(RGBDSequence(dev_sequence), "sess3", "r1", max_frames=12):
            frames.put(item.payload)
        time.sleep(2.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        frames = [d for t, d, _ in read_messages(tmp_path / "sess3.mcap") if t == "/twohr/r1/frames"]
        # with --record-frames each frame is ~0.2 MB and chunks are 256 kB: all but the last chunk's frames are on disk
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
