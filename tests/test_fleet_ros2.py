"""ROS 2 by robot on a fleet's router (loopback, real Zenoh router under the fleet's access list): a robot reads and
writes its own namespace, reads the other robots' poses, odometry, paths and transforms and nothing else of theirs,
may not publish the stack's global topics, and its rmw_zenoh liveliness tokens stay in its namespace. Robot ids
that are ROS 2's or the bridge's global names are refused at ``twohr keys add``."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
import zenoh

from twohr.bus import BusConfig, free_port, open_session
from twohr.identity import load_identity
from twohr_app.access import ROS2_SHARED_TOPICS
from twohr_app.fleet import Fleet
from twohr_app.fleet_router import FleetRouter
from twohr_services.ros2 import msgs
from twohr_services.ros2.config import Ros2Config
from twohr_services.ros2.convert import PoseOutputs
from twohr_services.ros2.rmw import NodeInfo, topic_key, topic_key_any_hash


def twohr(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> tuple[Fleet, dict[str, Path]]:
    folder = tmp_path_factory.mktemp("ros2fleet") / "K"
    fleet = Fleet(folder)
    fleet.init()
    bundles = {robot: folder.parent / f"{robot}.bundle" for robot in ("a", "b")}
    for robot, bundle in bundles.items():
        fleet.add(robot, bundle)
    return fleet, bundles


def _join(identity, endpoint: str) -> zenoh.Session:
    return open_session(BusConfig(connect=[endpoint], identity=identity, user=None, password=None, config_file=None,
                                  shared_memory=False))


def test_the_grants_name_the_topics_the_ros2_service_publishes():
    """What every robot may read of the others is what the ros2 service publishes per robot, no more."""
    published = {topic.rsplit("/", 1)[-1] for topic in PoseOutputs(Ros2Config(enabled=True)).topics("b").values()}
    assert published | {Ros2Config().corrected_topic} == set(ROS2_SHARED_TOPICS)
    assert Ros2Config().robot_namespace("b") == "/b"


def test_a_robot_reads_and_writes_its_own_ros2_namespace_and_reads_only_the_others_poses(fleet):
    keys, bundles = fleet
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = FleetRouter(keys.service_folder("router"), [endpoint])
    sessions: list[zenoh.Session] = []
    try:
        stack = _join(keys.identity("ros2"), endpoint)  # the stack's ros2 service: the whole domain
        a, b = _join(load_identity(bundles["a"]), endpoint), _join(load_identity(bundles["b"]), endpoint)
        sessions += [stack, a, b]
        lock = threading.Lock()
        at_stack: Counter[tuple[str, bytes]] = Counter()
        tokens: list[str] = []

        def count(where: Counter[tuple[str, bytes]]):
            def on_sample(sample) -> None:
                with lock:
                    where[str(sample.key_expr), sample.payload.to_bytes()] += 1
            return on_sample

        image, odom, pose, tf = msgs.Image, msgs.Odometry, msgs.PoseStamped, msgs.TFMessage
        # a subscribes as a ROS 2 node would (any type hash) to b's topics, and greedily to b's and the whole domain
        as_ros = {"camera": topic_key_any_hash(0, "/b/camera/color/image_raw", image),
                  "odom": topic_key_any_hash(0, "/b/odom", odom), "pose": topic_key_any_hash(0, "/b/pose", pose),
                  "tf": topic_key_any_hash(0, "/b/tf", tf), "global tf": topic_key_any_hash(0, "/tf", tf)}
        asked = (*as_ros.values(), "0/b/**", "0/**", "0/*/camera/**")
        at_a = {expr: Counter() for expr in asked}
        for expr in asked:
            a.declare_subscriber(expr, count(at_a[expr]))
        stack.declare_subscriber("0/**", count(at_stack))
        stack.liveliness().declare_subscriber("@ros2_lv/0/**", lambda s: tokens.append(str(s.key_expr)),
                                              history=True)
        time.sleep(1.5)

        of_b = {"camera": topic_key(0, "/b/camera/color/image_raw", image), "odom": topic_key(0, "/b/odom", odom),
                "pose": topic_key(0, "/b/pose", pose), "tf": topic_key(0, "/b/tf", tf),
                "depth": topic_key(0, "/b/camera/aligned_depth_to_color/image_raw", image)}
        for _ in range(5):
            for name, key_expr in of_b.items():
                b.put(key_expr, name.encode())
            stack.put(topic_key(0, "/tf", tf), b"stack tf")
            stack.put(topic_key(0, "/diagnostics", msgs.DiagnosticArray), b"stack diagnostics")
            # a writes its own namespace and rosout; the stack's topics and b's it may not
            for key_expr in (topic_key(0, "/a/odom", odom), topic_key(0, "/rosout", image),
                             topic_key(0, "/tf", tf), topic_key(0, "/tf_static", tf), topic_key(0, "/clock", image),
                             topic_key(0, "/diagnostics", msgs.DiagnosticArray), topic_key(0, "/b/odom", odom),
                             topic_key(0, "/camera/color/image_raw", image)):
                a.put(key_expr, b"from a")
        # a's node in its namespace, with a publisher of its own; a node in b's, in the root namespace, a publisher
        # on /tf: refused
        node = NodeInfo(session_id=str(a.zid()), node_id=1, namespace="/a", name="driver")
        held = [a.liveliness().declare_token(node.node_token()),
                a.liveliness().declare_token(node.endpoint_token(2, "MP", "/a/odom", odom)),
                a.liveliness().declare_token(node.endpoint_token(3, "MS", "/b/pose", pose))]
        outside = [NodeInfo(session_id=str(a.zid()), node_id=4, namespace="/b", name="driver").node_token(),
                   NodeInfo(session_id=str(a.zid()), node_id=5, namespace="/", name="a").node_token(),
                   node.endpoint_token(6, "MP", "/tf", tf), node.endpoint_token(7, "MS", "/b/camera/image", image),
                   NodeInfo(session_id=str(a.zid()), node_id=8, namespace="/ab", name="x").node_token()]
        held += [a.liveliness().declare_token(token) for token in outside]
        time.sleep(1.5)
        with lock:
            got_a, got_stack = {expr: dict(counts) for expr, counts in at_a.items()}, dict(at_stack)
        # b's pose, odometry and transforms reach a, its cameras never, whatever a asked for (what a put itself
        # it gets straight from its own session)
        got_a = {expr: {k: n for k, n in got.items() if k[1] != b"from a"} for expr, got in got_a.items()}
        assert {name: sum(got_a[expr].values()) for name, expr in as_ros.items()} == {
            "camera": 0, "odom": 5, "pose": 5, "tf": 5, "global tf": 5}, got_a
        for expr in ("0/b/**", "0/**", "0/*/camera/**"):
            assert not [k for k in got_a[expr] if "camera" in k[0] or "diagnostics" in k[0]], got_a[expr]
        assert got_a["0/b/**"] == {(of_b[name], name.encode()): 5 for name in ("odom", "pose", "tf")}, got_a
        # of what a put, its own namespace and /rosout arrive; the stack's global topics and b's do not
        assert {k: n for (k, payload), n in got_stack.items() if payload == b"from a"} == {
            topic_key(0, "/a/odom", odom): 5, topic_key(0, "/rosout", image): 5}, got_stack
        assert got_stack[topic_key(0, "/tf", tf), b"stack tf"] == 5 and got_stack[of_b["camera"], b"camera"] == 5
        assert sorted(tokens) == sorted([node.node_token(), node.endpoint_token(2, "MP", "/a/odom", odom),
                                         node.endpoint_token(3, "MS", "/b/pose", pose)]), tokens
        for token in held:
            token.undeclare()
    finally:
        for session in sessions:
            session.close()
        router.close()


@pytest.mark.parametrize("robot", ["tf", "tf_static", "clock", "rosout", "parameter_events", "diagnostics", "camera",
                                   "x\n", "a/b", "../a", "maps"])
def test_reserved_and_malformed_robot_ids_are_refused_in_one_line(fleet, robot):
    keys, _ = fleet
    out = keys.folder.parent / "refused.bundle"
    done = twohr("keys", "add", str(keys.folder), robot, "--out", str(out))
    assert done.returncode == 2 and not out.exists(), done
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr, done.stderr
    assert "robot id" in done.stderr
    assert robot not in keys.read().robots
