"""The gateway's live view on a real Zenoh router, fed as the stack feeds it: a pose is drawn for the robot whose
session it is. Robot b speaking for robot a's session (a session id is no secret: every robot reads a's poses), and a
robot that runs no session, draw nothing and make no channel."""

from __future__ import annotations

import time

from twohr import keys
from twohr.bus import free_port, open_session
from twohr.config import PipelineConfig
from twohr.messages import ControlMsg, PoseMsg, encode
from twohr.service import declare_publisher
from twohr_services.gateway.live import BusLiveView


def pose(robot: str, session: str, frame: int) -> bytes:
    return encode(PoseMsg(session_id=session, robot_id=robot, frame_index=frame, stamp=1000.0 + frame,
                          position=[0.1 * frame, 0.0, 0.0], orientation=[0.0, 0.0, 0.0, 1.0], status="tracking"))


def test_a_pose_is_drawn_only_for_the_robot_whose_session_it_is(bus_config, foxglove_listener):
    session = open_session(bus_config)
    port = free_port()
    live = BusLiveView(session, "127.0.0.1", port)
    publishers = {}

    def put(robot: str, stream: str, payload: bytes) -> None:
        key = keys.key(robot, stream)
        if key not in publishers:
            publishers[key] = declare_publisher(session, key)
        publishers[key].put(payload)

    try:
        listener = foxglove_listener(f"ws://127.0.0.1:{port}")
        time.sleep(0.5)  # the live view's subscribers and the listener are up
        put("a", keys.CONTROL, encode(ControlMsg(session_id="s-a", robot_id="a", frame_index=-1, stamp=time.time(),
                                                 command="start", config=PipelineConfig())))
        deadline = time.monotonic() + 10
        while not any(topic.startswith("/a/") for topic in listener.topics()):
            assert time.monotonic() < deadline, listener.topics()
            time.sleep(0.05)
        for frame in range(3):
            put("a", "pose", pose("a", "s-a", frame))
            put("b", "pose", pose("b", "s-a", frame))  # b on a's session
            put("ghost", "pose", pose("ghost", "s-ghost", frame))  # a robot that runs nothing
        deadline = time.monotonic() + 10
        while live.malformed < 6:
            assert time.monotonic() < deadline, (live.malformed, listener.counts)
            time.sleep(0.05)
        time.sleep(0.5)
        drawn = {topic: n for topic, n in listener.counts.items() if "pose" in topic}
        assert drawn and all(topic.startswith("/a/") for topic in drawn) and max(drawn.values()) == 3, drawn
        assert not any(topic.startswith(("/b/", "/ghost/")) for topic in listener.topics()), listener.topics()
    finally:
        live.close()
        session.close()
