"""The source service on a real Zenoh router: a paced replay starts its clock at the first answer."""

import threading
import time

from twohr import keys
from twohr.bus import open_session, wait_for_services
from twohr.dataset import RGBDSequence
from twohr.messages import ControlMsg, FrameMsg, PoseMsg, decode, encode
from twohr.service import declare_publisher
from twohr_services.source.service import SourceService

ROBOT = "paced"


def test_a_paced_replay_waits_for_the_first_answer_then_keeps_the_camera_rate(bus_config, static_synthetic_sequence):
    """The first frame of a session at rate 1 goes out at once; the next only once the first is answered (the
    tracker's first map, which on a slow CPU includes the network's warm-up), and from then on at the camera's
    rate: no frame is sent into a pipeline that cannot take it yet."""
    sequence = RGBDSequence(static_synthetic_sequence)
    frames = 10
    source = SourceService(bus_config, data_roots=[static_synthetic_sequence.parent])
    stop = threading.Event()
    thread = threading.Thread(target=source.run, args=(stop,), daemon=True)
    thread.start()
    client = open_session(bus_config)
    arrivals: list[tuple[float, int]] = []
    try:
        wait_for_services(client, ["source"], timeout=10)
        client.declare_subscriber(keys.key(ROBOT, "frames"), lambda sample: arrivals.append(
            (time.monotonic(), decode(sample.payload.to_bytes(), FrameMsg, only=())[0].frame_index)))
        control = ControlMsg(session_id="paced01", robot_id=ROBOT, frame_index=-1, stamp=time.time(),
                             command="start", sequence=static_synthetic_sequence.name, rate=1.0, max_frames=frames)
        declare_publisher(client, keys.key(ROBOT, keys.CONTROL)).put(encode(control))
        time.sleep(1.5)  # no answer yet: the first map is still being made
        assert [index for _, index in arrivals] == [0]
        answered_at = time.monotonic()
        declare_publisher(client, keys.key(ROBOT, "pose")).put(encode(PoseMsg(
            session_id="paced01", robot_id=ROBOT, frame_index=0, stamp=float(sequence.stamps[0]),
            position=[0, 0, 0], orientation=[0, 0, 0, 1], status="init")))
        deadline = time.monotonic() + 10
        while len(arrivals) < frames and time.monotonic() < deadline:
            time.sleep(0.02)
        assert [index for _, index in arrivals] == list(range(frames))
        # frame 1 at once, frames 2..9 at the recorded pace after it
        assert arrivals[1][0] - answered_at < 0.3, arrivals[1][0] - answered_at
        played = arrivals[-1][0] - arrivals[1][0]
        recorded = float(sequence.stamps[frames - 1] - sequence.stamps[1])
        assert abs(played - recorded) < 0.15, (played, recorded)
    finally:
        stop.set()
        thread.join(5)
        client.close()
