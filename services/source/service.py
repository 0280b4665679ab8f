"""The source service: plays sequences on ``twohr/<robot>/frames`` when the gateway says so, or
relays frames that any camera driver publishes on ``twohr/<robot>/camera`` (a camera session admitted at a lower
``rate`` than its camera's: one frame per ``1/rate`` of camera time, :class:`~twohr.rates.RateThinning`).

Flow control: at ``rate`` 0 the source plays as fast as the pipeline keeps up, keeping at most
``window`` frames in flight (sent but not yet answered by a pose); at ``rate`` > 0 it plays in
(scaled) real time and the services' queues decide what is dropped, once the first frame is answered: like a robot
that waits for its first map before it moves, the replay does not count the session's start-up (the first
keyframe, on a network that may be compiled and timed for it) as frames dropped.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path

from twohr import keys
from twohr.bus import BusConfig, bus_from_args
from twohr.dataset import RGBDSequence
from twohr.errors import TwohrError
from twohr.messages import ControlMsg, PoseMsg, StatusMsg, decode
from twohr.paths import resolve_under_roots
from twohr.rates import CameraRelay, ReplayPacer
from twohr.service import Service, one_line_errors, service_parser

from .core import frame_payloads

#: a paced replay waits at most this long for its first frame's answer before it plays on regardless
FIRST_ANSWER_TIMEOUT_S = 15.0


@dataclass
class Playback:
    control: ControlMsg
    stop: threading.Event = field(default_factory=threading.Event)
    sent: int = 0
    answered: int = 0
    progress: threading.Condition = field(default_factory=threading.Condition)
    thread: threading.Thread | None = None
    relay: CameraRelay | None = None  # a camera session's: its camera's frames into it


class SourceService(Service):
    name = "source"

    def __init__(self, bus: BusConfig | None = None, data_roots: list[Path] | None = None, window: int = 2) -> None:
        super().__init__(bus, queue_size=64, policy="backpressure")
        self.data_roots = data_roots or [Path.cwd()]
        self.window = window
        self.playbacks: dict[str, Playback] = {}  # by robot id

    def subscriptions(self) -> list[str]:
        # poses answer frames; so does the tracker's "relocalising" status for a frame it could give no pose
        return [keys.all_robots(keys.CONTROL), keys.all_robots("pose"), keys.all_robots("status"),
                keys.all_robots(keys.RAW_CAMERA)]

    def handle(self, key: str, payload: bytes) -> None:
        robot, stream = keys.parse(key)
        if stream == keys.CONTROL:
            control, _ = decode(payload, ControlMsg)
            if control.robot_id != robot:
                raise TwohrError(f"control for robot {control.robot_id} published on {key}")
            if control.command == "start" and keys.edge_robot(control.tracker) is None:
                self._start(control)  # (a robot that tracks itself relays its camera to its own tracker)
            elif control.command == "stop":  # a move is the tracker's: the frames go on as they were
                self._stop(robot, control.session_id)
        elif stream in ("pose", "status"):
            answer, _ = decode(payload, PoseMsg if stream == "pose" else StatusMsg)
            if stream == "status" and (answer.service, answer.state) != ("tracker", "relocalising"):
                return
            playback = self.playbacks.get(robot)
            if playback and playback.control.session_id == answer.session_id:
                with playback.progress:
                    playback.answered += 1
                    playback.progress.notify_all()
        elif stream == keys.RAW_CAMERA:
            self._relay(robot, payload)

    def _start(self, control: ControlMsg) -> None:
        self._stop(control.robot_id)
        playback = Playback(control, relay=None if control.sequence else CameraRelay(control.session_id, control.rate))
        self.playbacks[control.robot_id] = playback
        if control.sequence:
            playback.thread = threading.Thread(target=self._play, args=(playback,), daemon=True,
                                               name=f"play-{control.session_id}")
            playback.thread.start()
        else:
            self.report(control, "live", "relaying twohr/<robot>/camera")

    def _stop(self, robot: str, session_id: str | None = None) -> None:
        playback = self.playbacks.get(robot)
        if playback and (session_id is None or playback.control.session_id == session_id):
            if not playback.control.sequence:
                self.report(playback.control, "stopped", "camera session ended", frames=playback.sent)
            playback.stop.set()
            with playback.progress:
                playback.progress.notify_all()
            if playback.thread is not None:
                playback.thread.join(timeout=5)
            self.playbacks.pop(robot, None)

    def _play(self, playback: Playback) -> None:
        control = playback.control
        try:
            folder = resolve_under_roots(control.sequence, self.data_roots)
            sequence = RGBDSequence(folder, camera=control.config.camera)
        except TwohrError as exc:
            self.report(control, "error", str(exc))
            return
        pacer = ReplayPacer(speed=control.rate)
        frames_key = keys.key(control.robot_id, "frames")
        stop = len(sequence) if control.max_frames is None else min(len(sequence), control.start + control.max_frames)
        self.report(control, "started", sequence.name, frames=max(0, stop - control.start))

        def pace(stamp: float) -> None:
            if control.rate > 0:
                if playback.sent == 1:  # the camera's clock starts once the first frame is answered
                    with playback.progress:
                        playback.progress.wait_for(lambda: playback.answered or playback.stop.is_set(),
                                                   FIRST_ANSWER_TIMEOUT_S)
                    pacer.restart()
                pacer.wait(stamp, playback.stop)
                return
            with playback.progress:  # credit-based flow control
                while playback.sent - playback.answered >= self.window and not playback.stop.is_set():
                    playback.progress.wait(0.5)

        for item in frame_payloads(sequence, control.session_id, control.robot_id, start=control.start,
                                   max_frames=control.max_frames, pace=pace):
            if playback.stop.is_set():
                break
            self.publish(frames_key, item.payload)
            playback.sent += 1
        state = "stopped" if playback.stop.is_set() else "finished"
        self.report(control, state, sequence.name, frames=playback.sent, skipped=len(sequence.skipped))

    def _relay(self, robot: str, payload: bytes) -> None:
        playback = self.playbacks.get(robot)
        if playback is None or playback.control.sequence:
            return  # no live session for this robot
        relayed = playback.relay.relay(payload)
        if relayed is None:
            return  # the session was admitted at a lower rate than its camera's
        self.publish(keys.key(robot, "frames"), relayed)
        playback.sent = playback.relay.sent
        if playback.relay.status_due:
            self.report(playback.control, "relaying", frames=playback.sent)


@one_line_errors("source")
def main(argv: list[str] | None = None) -> None:
    parser = service_parser("source", __doc__)
    parser.add_argument("--data-root", action="append", default=None, help="folder sequences may come from")
    parser.add_argument("--window", type=int, default=2, help="frames in flight at rate 0")
    args = parser.parse_args(argv)
    bus = bus_from_args(args)
    roots = [Path(r) for r in args.data_root] if args.data_root else None
    SourceService(bus, roots, args.window).run_forever()
