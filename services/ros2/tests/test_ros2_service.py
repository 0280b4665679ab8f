"""The ros2 service on a real Zenoh router: poses out as rmw_zenoh samples (checked with rosbags), liveliness
tokens, attachments, the tracker's corrections as map -> odom, session statuses on /diagnostics, and a ROS 2
camera in as twohr frames."""

import threading
import time

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from twohr import keys
from twohr.bus import open_session, wait_for_services
from twohr.dataset import RGBDSequence
from twohr.messages import FrameMsg, PoseMsg, StatusMsg, decode, encode
from twohr.service import declare_publisher
from twohr_services.ros2 import msgs
from twohr_services.ros2.config import Ros2CameraInput, Ros2Config
from twohr_services.ros2.convert import frame_to_ros
from twohr_services.ros2.rmw import Attachment, topic_key
from twohr_services.ros2.service import Ros2Service, command

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def wait_until(condition, timeout=15.0):
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return condition()


@pytest.fixture
def ros2_service(bus_config):
    config = Ros2Config(enabled=True, camera_input=Ros2CameraInput(robot_id="cam1", namespace="/cam1"))
    service = Ros2Service(bus_config, config)
    stop = threading.Event()
    thread = threading.Thread(target=service.run, args=(stop,), daemon=True)
    thread.start()
    client = open_session(bus_config)
    wait_for_services(client, ["ros2"], timeout=15)
    yield service, client
    stop.set()
    thread.join(timeout=10)
    client.close()


def test_poses_become_ros2_samples_that_rosbags_decodes(ros2_service):
    service, client = ros2_service
    samples = []
    subscriber = client.declare_subscriber("0/**", lambda s: samples.append(
        (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment is not None else None)))
    publisher = declare_publisher(client, keys.key("live1", "pose"))
    n = 12
    for i in range(n):
        publisher.put(encode(PoseMsg(session_id="s1", robot_id="live1", frame_index=i, stamp=50.0 + i / 30,
                                     position=[0.01 * i, 0.0, 0.2], orientation=[0.0, 0.0, 0.0, 1.0],
                                     status="tracking", is_keyframe=i % 4 == 0)))
    assert wait_until(lambda: len(samples) >= 3 * n + 3)
    time.sleep(0.3)
    subscriber.undeclare()

    by_key: dict[str, list] = {}
    for key, payload, attachment in samples:
        by_key.setdefault(key, []).append((payload, attachment))
    expected = {topic_key(0, "/live1/pose", msgs.PoseStamped): n, topic_key(0, "/live1/odom", msgs.Odometry): n,
                topic_key(0, "/live1/tf", msgs.TFMessage): n, topic_key(0, "/live1/path", msgs.Path): 3}
    assert {k: len(v) for k, v in by_key.items()} == expected
    pose_key = topic_key(0, "/live1/pose", msgs.PoseStamped)
    assert pose_key.startswith("0/live1/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_")
    for key, items in by_key.items():
        ros_type = next(cls.__msgtype__ for cls in (msgs.PoseStamped, msgs.Odometry, msgs.TFMessage, msgs.Path)
                        if msgs.dds_type(cls) in key)
        decoded = [TYPESTORE.deserialize_cdr(payload, ros_type) for payload, _ in items]
        attachments = [Attachment.decode(attachment) for _, attachment in items]
        assert [a.sequence_number for a in attachments] == list(range(1, len(items) + 1))
        assert len({a.source_gid for a in attachments}) == 1
        if ros_type == "geometry_msgs/msg/PoseStamped":
            assert [m.pose.position.x for m in decoded] == pytest.approx([0.01 * i for i in range(n)])
            assert decoded[0].header.frame_id == "map" and decoded[5].header.stamp.sec == 50
        if ros_type == "nav_msgs/msg/Odometry":
            assert {(m.header.frame_id, m.child_frame_id) for m in decoded} == {("odom", "camera")}
        if ros_type == "tf2_msgs/msg/TFMessage":  # REP 105: map -> odom (no correction yet) with odom -> camera
            assert {tuple((t.header.frame_id, t.child_frame_id) for t in m.transforms) for m in decoded} == {
                (("map", "odom"), ("odom", "camera"))}
            assert all(m.transforms[0].transform.translation.x == 0 and m.transforms[0].transform.rotation.w == 1
                       for m in decoded)
            assert [m.transforms[1].transform.translation.x for m in decoded] == pytest.approx(
                [0.01 * i for i in range(n)])
        if ros_type == "nav_msgs/msg/Path":
            assert [len(m.poses) for m in decoded] == [1, 2, 3]
    assert service.health()["published"]["geometry_msgs/msg/PoseStamped"] == n

    tokens = sorted(str(reply.ok.key_expr) for reply in client.liveliness().get("@ros2_lv/0/**", timeout=2)
                    if reply.ok is not None)
    zid = str(service.session.zid())
    nodes = [t.split("/") for t in tokens if t.endswith("/NN/%/%live1/twohr")]
    assert len(nodes) == 1 and nodes[0][:3] == ["@ros2_lv", "0", zid] and nodes[0][3] == nodes[0][4]
    publishers = [t for t in tokens if "/MP/%/%live1/twohr/" in t]
    assert {t.split("/")[3] for t in publishers} == {nodes[0][3]}  # the node's own publishers
    assert sorted(t.split("/")[9] for t in publishers) == ["%live1%odom", "%live1%path", "%live1%pose", "%live1%tf"]
    assert all(t.endswith("/::,10:,:,:,,") for t in publishers)
    camera_subscriptions = [t for t in tokens if "/MS/%/%cam1/twohr/" in t]
    assert len(camera_subscriptions) == 4


def test_corrected_paths_become_a_nav_msgs_path(ros2_service):
    """The tracker's corrections (keyframes after bundle adjustment, then the refined trajectory) reach ROS 2 as
    nav_msgs/Path on <namespace>/path_corrected, decodable by rosbags, in the map frame; a live one moves
    map -> odom on tf and the map-frame PoseStamped of the poses that follow."""
    from twohr.messages import PathMsg, path_arrays
    from twohr.trajectory import Trajectory

    _, client = ros2_service
    samples, tfs, stamped = [], [], []
    key = topic_key(0, "/live2/path_corrected", msgs.Path)
    subscriber = client.declare_subscriber(key, lambda s: samples.append(s.payload.to_bytes()))
    tf_subscriber = client.declare_subscriber(topic_key(0, "/live2/tf", msgs.TFMessage),
                                              lambda s: tfs.append(s.payload.to_bytes()))
    pose_subscriber = client.declare_subscriber(topic_key(0, "/live2/pose", msgs.PoseStamped),
                                                lambda s: stamped.append(s.payload.to_bytes()))
    pose_publisher = declare_publisher(client, keys.key("live2", "pose"))
    publisher = declare_publisher(client, keys.key("live2", "path"))

    def pose(i: int, stamp: float, x: float) -> bytes:
        return encode(PoseMsg(session_id="s2", robot_id="live2", frame_index=i, stamp=stamp, position=[x, 0.0, 0.0],
                              orientation=[0.0, 0.0, 0.0, 1.0], status="tracking", is_keyframe=True))

    for i, (stamp, x) in enumerate(((10.0, 0.0), (10.5, 0.1), (11.0, 0.2))):  # online: keyframe 11.0 drifted 5 cm
        pose_publisher.put(pose(i, stamp, x))
    assert wait_until(lambda: len(tfs) >= 3)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 0.1, 0.25]
    corrected = Trajectory(np.array([10.0, 10.5, 11.0]), poses)
    live = PathMsg(session_id="s2", robot_id="live2", frame_index=30, stamp=11.0, final=False)
    publisher.put(encode(live, path_arrays(corrected)))
    assert wait_until(lambda: len(samples) >= 1)  # handled: map -> odom is now the keyframe's correction
    pose_publisher.put(pose(3, 11.5, 0.3))
    assert wait_until(lambda: len(tfs) >= 4 and len(stamped) >= 4)
    publisher.put(encode(live.model_copy(update={"final": True}), path_arrays(corrected)))
    assert wait_until(lambda: len(samples) >= 2)
    for sub in (subscriber, tf_subscriber, pose_subscriber):
        sub.undeclare()
    decoded = [TYPESTORE.deserialize_cdr(payload, "nav_msgs/msg/Path") for payload in samples]
    assert [[p.pose.position.x for p in m.poses] for m in decoded] == [pytest.approx([0.0, 0.1, 0.25])] * 2
    assert decoded[0].header.frame_id == "map" and decoded[0].poses[1].header.stamp.nanosec == 500_000_000
    transforms = [TYPESTORE.deserialize_cdr(payload, "tf2_msgs/msg/TFMessage").transforms for payload in tfs]
    assert [t[0].transform.translation.x for t in transforms] == pytest.approx([0.0, 0.0, 0.0, 0.05])
    assert [(t[0].header.frame_id, t[0].child_frame_id) for t in transforms] == [("map", "odom")] * 4
    assert [t[1].transform.translation.x for t in transforms] == pytest.approx([0.0, 0.1, 0.2, 0.3])  # online
    in_map = [TYPESTORE.deserialize_cdr(payload, "geometry_msgs/msg/PoseStamped") for payload in stamped]
    assert [m.pose.position.x for m in in_map] == pytest.approx([0.0, 0.1, 0.2, 0.35])
    assert {m.header.frame_id for m in in_map} == {"map"}


def test_a_degraded_session_status_reaches_diagnostics(ros2_service):
    """The tracker's ``degraded`` (and why, with its figures) on twohr/<robot>/status is a WARN on /diagnostics."""
    service, client = ros2_service
    samples = []
    subscriber = client.declare_subscriber(topic_key(0, "/diagnostics", msgs.DiagnosticArray),
                                           lambda s: samples.append(s.payload.to_bytes()))
    publisher = declare_publisher(client, keys.key("live3", "status"))
    detail = "keyframe job 42 frames late (CPU 35 ms per frame)"
    for state, why in (("degraded", detail), ("ok", "keeping up (CPU 20 ms per frame)")):
        publisher.put(encode(StatusMsg(session_id="s3", robot_id="live3", frame_index=-1, stamp=time.time(),
                                       service="tracker", state=state, detail=why,
                                       counters={"dropped_percent": 0, "keyframe_lag": 42, "cpu_ms_per_frame": 35})))
    assert wait_until(lambda: len(samples) >= 2)
    subscriber.undeclare()
    decoded = [TYPESTORE.deserialize_cdr(payload, "diagnostic_msgs/msg/DiagnosticArray") for payload in samples]
    assert [[s.level for s in m.status] for m in decoded] == [[1], [0]]
    degraded = decoded[0].status[0]
    assert (degraded.name, degraded.message, degraded.hardware_id) == ("twohr/live3/tracker", detail, "live3")
    assert {kv.key: kv.value for kv in degraded.values} == {"state": "degraded", "session_id": "s3",
                                                            "dropped_percent": "0", "keyframe_lag": "42",
                                                            "cpu_ms_per_frame": "35"}
    assert service.health()["published"]["diagnostic_msgs/msg/DiagnosticArray"] == 2
    tokens = [str(reply.ok.key_expr) for reply in client.liveliness().get("@ros2_lv/0/**", timeout=2)
              if reply.ok is not None]
    assert any("/MP/%/%live3/twohr/%diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/RIHS01_5a8a" in t
               for t in tokens), tokens


def test_ros2_camera_images_become_twohr_frames(ros2_service, dev_sequence):
    _, client = ros2_service
    received = []
    subscriber = client.declare_subscriber(keys.key("cam1", keys.RAW_CAMERA),
                                           lambda s: received.append(decode(s.payload.to_bytes(), FrameMsg)))
    sequence = RGBDSequence(dev_sequence)
    topics = Ros2CameraInput(robot_id="cam1", namespace="/cam1").topics()
    color_pub = declare_publisher(client, topic_key(0, topics["color"], msgs.Image))
    depth_pub = declare_publisher(client, topic_key(0, topics["depth"], msgs.Image))
    info_pub = declare_publisher(client, topic_key(0, topics["info"], msgs.CameraInfo))

    def send(frame) -> None:
        raw = np.round(frame.depth * sequence.camera.depth_factor).astype(np.uint16)
        color, depth, info = frame_to_ros(frame.stamp, frame.rgb, raw, sequence.camera)
        info_pub.put(msgs.serialize(info))
        depth_pub.put(msgs.serialize(depth))
        color_pub.put(msgs.serialize(color))

    # the subscriber reaches the service through the router a moment after it is declared: a first frame, sent
    # until one comes back, tells when the route is there (then the frames under test, none lost)
    first = sequence.read(0)
    assert wait_until(lambda: send(first) or len(received) > 0, timeout=20.0), ros2_service[0].health()
    time.sleep(0.5)
    received.clear()
    n = 4
    originals = [sequence.read(index) for index in range(1, n + 1)]
    for frame in originals:
        send(frame)
    assert wait_until(lambda: len(received) >= n), (len(received), ros2_service[0].health())
    subscriber.undeclare()
    assert len(received) == n
    for frame, (message, arrays) in zip(originals, received, strict=True):
        assert message.robot_id == "cam1" and message.stamp == pytest.approx(frame.stamp)
        assert message.camera.fx == pytest.approx(sequence.camera.fx) and message.camera.cx == pytest.approx(
            sequence.camera.cx)
        assert arrays["depth"].dtype == np.uint16 and arrays["depth"].shape == frame.depth.shape
        assert np.abs(arrays["depth"] / 1000.0 - frame.depth).max() <= 0.0006
        assert np.abs(arrays["rgb"].astype(int) - frame.rgb).mean() < 3  # JPEG on the twohr camera key


def test_command_line_for_twohr_up():
    argv = command("tcp/127.0.0.1:7447", domain_id=3)
    assert argv[1:] == ["-m", "twohr_services.ros2", "--router", "tcp/127.0.0.1:7447", "--domain", "3"]


def test_bad_settings_exit_2_with_one_line(tmp_path):
    import subprocess
    import sys

    def run(*args):
        return subprocess.run([sys.executable, "-m", "twohr_services.ros2", *args], capture_output=True, text=True,
                              timeout=60)

    assert run("--help").returncode == 0
    proc = run("--domain", "999")
    assert proc.returncode == 2 and proc.stderr.strip().splitlines()[-1].endswith(
        "error: domain_id: Input should be less than or equal to 232")
    config = tmp_path / "ros2.yaml"
    config.write_text("ros2:\n  map_frame: 'a b'\n")
    proc = run("--config", str(config))
    assert proc.returncode == 2 and "map_frame" in proc.stderr.strip().splitlines()[-1]
    proc = run("--odom-frame", "map")
    assert proc.returncode == 2 and proc.stderr.strip().splitlines()[-1].endswith(
        "error: map_frame, odom_frame and camera_frame must differ, got 'map', 'map' and 'camera'")
