"""A robot's own tracker (``twohr camera --edge``): the robot tracks itself, beside its camera, in one process.

The camera's frames go to the tracker in memory: no per-frame stream leaves the robot. The tracker is the stack's
(:class:`~twohr_services.tracker.service.TrackerService`: the same schedule, poses, paths, status and final
trajectory on the same keys), built with the camera as its frame inlet (:class:`CameraInlet`) and its own stages
(:class:`EdgeStages`), serving this robot's sessions only, as tracker replica ``edge+<robot>``: the gateway places a
camera session of the robot on it while its liveliness token is alive.

Where each network runs is configuration (``--server-stages``, default ``detector``): the stack's replicas answer
those (the detector gets a keyframe's colour JPEG alone, about 86 kB for 640x480), the others run here (yolo at
320 px and the matcher: a match query's float32 descriptors would cost more on the link than the matching costs
here). A robot whose link to the stack drops keeps tracking in its local map (its keyframe jobs find no replica
and are skipped: no new keyframes until the link is back), and says so on its status and its console.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, replace

from twohr import keys
from twohr.bus import BusConfig
from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics
from twohr.errors import TwohrError
from twohr.messages import ControlMsg, FrameMsg, StatusMsg, encode
from twohr.rates import CameraRelay
from twohr.replicas import Replicas
from twohr_services.tracker.remote import RemoteStages
from twohr_services.tracker.service import TrackerService
from twohr_services.tracker.stages import Stages

from .pipeline import local_stages

#: the networks the stack answers for a robot that tracks itself, by default
SERVER_STAGES = ("detector",)
#: how long a keyframe job waits for a replica of a server stage to appear (s): past it the link is taken as down
#: and the job is skipped (the stack's trackers wait 10 s, for replicas that restart)
LINK_WAIT_S = 1.0

#: how long the camera waits for a session before it says where one may have gone (s)
WAIT_HINT_S = 30.0
#: how long ending the robot's sessions may take when the camera stops (s)
FINISH_TIMEOUT_S = 300.0

log = logging.getLogger("twohr.edge")


@dataclass
class Served:
    """The session this robot's tracker serves, and its camera's frames into it."""

    control: ControlMsg
    relay: CameraRelay


def parse_server_stages(value: str) -> tuple[str, ...]:
    """``--server-stages``: comma-separated names of :data:`twohr.keys.NETWORK_SERVICES`, or ``none``."""
    from twohr.errors import ConfigError

    names = tuple(dict.fromkeys(n.strip() for n in value.split(",") if n.strip() and n.strip() != "none"))
    unknown = [n for n in names if n not in keys.NETWORK_SERVICES]
    if unknown:
        raise ConfigError(f"--server-stages {value!r}: {', '.join(unknown)} is no network stage (name some of "
                          f"{', '.join(keys.NETWORK_SERVICES)}, or none)")
    return names


class EdgeStages:
    """The stages of a robot's own tracker: the ``server_stages`` asked of the stack (:class:`RemoteStages`, a job
    waiting :data:`LINK_WAIT_S` for a replica), the other networks in this process (compiled once per camera and
    config)."""

    def __init__(self, server_stages: tuple[str, ...]) -> None:
        self.server_stages = tuple(server_stages)
        self.remote = RemoteStages(wait_for_one=LINK_WAIT_S)
        self.local: dict[tuple, Stages] = {}  # the stages that run here, by config and camera size
        self.local_lock = threading.Lock()

    @property
    def replicas(self) -> dict[str, Replicas]:
        return self.remote.replicas

    def open(self, session) -> None:
        self.remote.open(session)

    def stages_for(self, header: FrameMsg, config: PipelineConfig) -> Stages:
        remote = self.remote.stages_for(header, config)
        local = self.local_for(config, header.camera)
        if local is None:
            return remote
        asked = {"detector": ("detect",), "yolo": ("dynamic_mask",), "matcher": ("match", "match_sets")}
        return replace(local, **{field: getattr(remote, field) for name in self.server_stages for field in asked[name]})

    def local_for(self, config: PipelineConfig, camera: CameraIntrinsics) -> Stages | None:
        here = tuple(name for name in keys.NETWORK_SERVICES if name not in self.server_stages)
        if not here:
            return None
        key = (config.model_dump_json(include={"detector", "yolo", "matcher"}), camera.width, camera.height)
        with self.local_lock:  # the camera's thread warms them, the service's thread asks for them
            if key not in self.local:
                self.local[key] = local_stages(config, camera, here=here)
            return self.local[key]

    def reachable(self) -> bool:
        """Whether every server stage has a replica in reach (the link to the stack, and the stack's replicas)."""
        return all(self.replicas[name].alive() for name in self.server_stages)


class CameraInlet:
    """The frames of a robot's own tracker: its camera's, in memory, into the one session the tracker serves (a new
    session ends the one before); the sessions: its robot's, assigned to its replica."""

    one_session = True

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.served: Served | None = None

    def subscriptions(self) -> list[str]:
        return []  # no frame comes over the bus

    def control_keys(self) -> list[str]:
        return [keys.key(self.robot, keys.CONTROL)]

    def heard(self, control: ControlMsg, replica: str) -> None:
        pass  # its frames come in memory, none off the bus

    def takes(self, control: ControlMsg, replica: str) -> bool:
        return control.tracker == replica

    def wants(self, robot: str) -> bool:
        return robot == self.robot

    def started(self, control: ControlMsg) -> None:
        self.served = Served(control, CameraRelay(control.session_id, control.rate))

    def stopped(self, session_id: str) -> None:
        if self.served is not None and self.served.control.session_id == session_id:
            self.served = None


class LinkWatch:
    """Says when the server stages go out of reach (the link to the stack, or the stack's replicas): on the console
    at once, and on the session's status once the stack hears the robot again."""

    def __init__(self, stages: EdgeStages, report) -> None:
        self.stages, self.report = stages, report
        self.session_id: str | None = None  # the session watched
        self.online: bool | None = None  # the server stages' replicas in reach, as last seen
        self.offline_since: float | None = None  # when they went out of reach (monotonic s)

    def check(self, served: Served | None) -> None:
        online = self.stages.reachable()
        if served is None:
            return
        if served.control.session_id != self.session_id:  # a new session: its link is looked at afresh
            self.session_id, self.online, self.offline_since = served.control.session_id, None, None
        if online == self.online:
            return
        stages = ", ".join(self.stages.server_stages)
        if not online:
            self.offline_since = time.monotonic()
            log.warning("the stack is out of reach: tracking in the local map, no new keyframes from its %s until "
                        "the link is back", stages)
        elif self.offline_since is not None:
            detail = (f"the stack was out of reach for {time.monotonic() - self.offline_since:.1f} s: tracked in the "
                      f"local map meanwhile, without new keyframes; keyframes from its {stages} again")
            log.info("%s", detail)
            self.report(served.control, "online", detail)
            self.offline_since = None
        self.online = online


class EdgeTracker:
    """Robot ``robot``'s own tracker: the stack's :class:`TrackerService` built with its camera's inlet
    (:class:`CameraInlet`, fed by :meth:`feed`) and its stages (:class:`EdgeStages`: the ``server_stages`` asked of
    the stack, the other networks run in this process), as tracker replica ``edge+<robot>``."""

    def __init__(self, bus: BusConfig, robot: str, server_stages: tuple[str, ...] = SERVER_STAGES) -> None:
        self.robot, self.replica = robot, keys.edge_replica(robot)
        self.camera = CameraInlet(robot)
        self.stages = EdgeStages(server_stages)
        # a map's snapshot serves a move; its frames cannot move
        self.service = TrackerService(bus, snapshots=False, inlet=self.camera, networks=self.stages,
                                      replica=self.replica)
        self.link = LinkWatch(self.stages, self.service.report)

    def warm(self, camera: CameraIntrinsics) -> None:
        """Compile the networks that run here for this camera with the default config now, not on a session's
        first frame (a second and a half of frames dropped at 30 Hz)."""
        self.service.warm_up(f"the networks here ({camera.width}x{camera.height})",
                             lambda: self.stages.local_for(PipelineConfig(), camera))

    def upstream_bytes(self) -> int:
        """What this robot sent the stack so far: its results and its keyframe jobs (payloads)."""
        return self.service.published_bytes + self.stages.remote.bytes_sent()

    def feed(self, payload: bytes) -> bool:
        """One camera frame message: into the session this robot's tracker serves, if any (False: none, or the
        frame is above the session's admitted rate)."""
        served = self.camera.served
        self.link.check(served)
        relayed = None if served is None else served.relay.relay(payload)
        if relayed is None:
            return False
        self.service.queue_frame(keys.key(self.robot, "frames"), relayed)
        if served.relay.status_due:  # as the stack's source counts a camera's frames
            self.report_relayed()
        return True

    def report_relayed(self) -> None:
        """The frames relayed into the session so far, on its status (every few frames, and after the camera's
        last: the gateway then knows them all)."""
        served = self.camera.served
        if served is None:
            return
        status = StatusMsg(session_id=served.control.session_id, robot_id=self.robot, frame_index=-1,
                           stamp=time.time(), service="source", state="relaying",
                           counters={"frames": served.relay.sent})
        self.service.publish(keys.key(self.robot, "status"), encode(status))

    def end_sessions(self, timeout: float) -> None:
        """End every session still served here as the gateway's stop would (its final path goes out)."""
        self.camera.served = None
        self.service.end_sessions(timeout)


def run_edge(bus: BusConfig, robot: str, payloads, server_stages: tuple[str, ...], linger_s: float,
             camera: CameraIntrinsics | None = None, say=print) -> int:
    """``twohr camera --edge``: the camera's ``payloads`` into robot ``robot``'s own tracker, in this process, from
    the start of its session (``camera``, where known before the first frame: the networks here are compiled for it
    first). After the last frame it waits up to ``linger_s`` for the session to be stopped (its refined trajectory
    then goes out), and ends any still running itself. Prints what it sent upstream."""
    tracker = EdgeTracker(bus, robot, server_stages)
    service = tracker.service
    service.take_priority()  # a frame's pose goes first on the robot too (where it may raise itself)
    stop = threading.Event()
    thread = threading.Thread(target=service.run, args=(stop,), name="edge-tracker", daemon=True)
    thread.start()
    if not service.ready.wait(30):
        stop.set()
        raise TwohrError(f"robot {robot}'s tracker could not join the bus within 30 s")
    if camera is not None:  # compiled before it says it is ready: a session's first frames find them warm
        tracker.warm(camera)
    time.sleep(0.5)  # the gateway hears its token before the first session asks for it
    say(f"robot {robot} tracks itself (tracker {tracker.replica}); the stack answers its "
        f"{', '.join(server_stages) or 'nothing'}; start its session with POST /sessions "
        f"{{\"source\": \"camera\", \"robot_id\": \"{robot}\"}}")
    fed, frames, t0 = 0, 0, time.monotonic()
    try:
        hint_at = time.monotonic() + WAIT_HINT_S
        while tracker.camera.served is None and thread.is_alive():
            time.sleep(0.05)  # frames go out when a session wants them: a replay starts with its session
            if time.monotonic() > hint_at:
                hint_at = float("inf")
                say(f"no session has come to robot {robot}'s own tracker yet; if one runs, the gateway placed it "
                    "elsewhere: was this robot's key made with twohr keys add --edge, and is it the camera session?")
        t0 = time.monotonic()
        for payload in payloads:
            if not thread.is_alive():
                raise TwohrError(f"robot {robot}'s tracker stopped (its log above says why)")
            frames += 1
            fed += tracker.feed(payload)
        tracker.report_relayed()
        elapsed = max(time.monotonic() - t0, 1e-9)
        deadline = time.monotonic() + linger_s
        while service.sessions and time.monotonic() < deadline and thread.is_alive():
            time.sleep(0.2)  # the session's stop, from the gateway
    except KeyboardInterrupt:
        elapsed = max(time.monotonic() - t0, 1e-9)
    finally:
        tracker.end_sessions(timeout=30)
        stop.set()
        thread.join(timeout=FINISH_TIMEOUT_S)  # the final bundle adjustment and path of a long session
    sent = tracker.upstream_bytes()
    jobs = {name: replicas.bytes_sent for name, replicas in tracker.stages.replicas.items() if replicas.bytes_sent}
    say(f"tracked {fed} of {frames} frames here in {elapsed:.1f} s ({frames / elapsed:.1f} FPS), {sent} bytes "
        f"({sent / elapsed:.0f} bytes/s upstream): keyframe jobs {jobs or 0}, results {service.published_bytes}")
    return 0
