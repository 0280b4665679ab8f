"""A robot's own tracker (``twohr camera --edge``): the robot tracks itself, beside its camera, in one process.

The camera's frames go to the tracker in memory: no per-frame stream leaves the robot. The tracker is the stack's
(:class:`~twohr_services.tracker.service.TrackerService`: the same schedule, poses, paths, status and final
trajectory on the same keys), serving this robot's sessions only, as tracker replica ``edge+<robot>``: the gateway
places a camera session of the robot on it while its liveliness token is alive.

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


class EdgeTracker(TrackerService):
    """Robot ``robot``'s own tracker: fed the camera's frames by :meth:`feed`, the ``server_stages`` asked of the
    stack and the other networks run in this process."""

    def __init__(self, bus: BusConfig, robot: str, server_stages: tuple[str, ...] = SERVER_STAGES) -> None:
        super().__init__(bus, snapshots=False)  # a map's snapshot serves a move; its frames cannot move
        self.robot, self.server_stages = robot, tuple(server_stages)
        self.replica = keys.edge_replica(robot)
        self.served: Served | None = None
        self.online: bool | None = None  # the server stages' replicas in reach, as last seen
        self.offline_since: float | None = None  # when they went out of reach (monotonic s)
        self.published_bytes, self.bytes_lock = 0, threading.Lock()
        self.ready = threading.Event()  # serving: its token declared, its sessions heard
        self.local: dict[tuple, Stages] = {}  # the stages that run here, by config and camera size
        self.local_lock = threading.Lock()

    def subscriptions(self) -> list[str]:
        return [keys.merged_key()]  # its frames come from the camera, in memory; the shared maps' merges

    def control_keys(self) -> list[str]:
        return [keys.key(self.robot, keys.CONTROL)]

    def takes(self, control: ControlMsg) -> bool:
        return control.tracker == self.replica

    def on_start(self) -> None:
        self.replicas = {name: Replicas(self.session, name, wait_for_one=LINK_WAIT_S)
                         for name in keys.NETWORK_SERVICES}

    def process_one(self, timeout: float = 0.2) -> bool:
        self.ready.set()  # the shell's loop runs: the token and the control subscription are declared
        return super().process_one(timeout)

    def stages_for(self, header: FrameMsg, config: PipelineConfig) -> Stages:
        """The server stages over the bus, the others in this process (compiled once per camera and config)."""
        remote = super().stages_for(header, config)
        local = self._local_stages(config, header.camera)
        if local is None:
            return remote
        asked = {"detector": ("detect",), "yolo": ("dynamic_mask",), "matcher": ("match", "match_sets")}
        return replace(local, **{field: getattr(remote, field) for name in self.server_stages for field in asked[name]})

    def _local_stages(self, config: PipelineConfig, camera: CameraIntrinsics) -> Stages | None:
        here = tuple(name for name in keys.NETWORK_SERVICES if name not in self.server_stages)
        if not here:
            return None
        key = (config.model_dump_json(include={"detector", "yolo", "matcher"}), camera.width, camera.height)
        with self.local_lock:  # the camera's thread warms them, the service's thread asks for them
            if key not in self.local:
                self.local[key] = local_stages(config, camera, here=here)
            return self.local[key]

    def warm(self, camera: CameraIntrinsics) -> None:
        """Compile the networks that run here for this camera with the default config now, not on a session's
        first frame (a second and a half of frames dropped at 30 Hz)."""
        self.warm_up(f"the networks here ({camera.width}x{camera.height})",
                     lambda: self._local_stages(PipelineConfig(), camera))

    def publish(self, key: str, payload: bytes, attachment: str | None = None) -> None:
        with self.bytes_lock:  # the per-frame, finishing and camera threads publish
            self.published_bytes += len(payload)
        super().publish(key, payload, attachment)

    def upstream_bytes(self) -> int:
        """What this robot sent the stack so far: its results and its keyframe jobs (payloads)."""
        return self.published_bytes + sum(r.bytes_sent for r in self.replicas.values())

    def on_session_start(self, control: ControlMsg) -> None:
        for session_id in [s for s in self.serving if s != control.session_id]:  # one robot, one session
            self.on_session_stop(session_id)
            self.session_configs.pop(session_id, None)
        super().on_session_start(control)
        self.served = Served(control, CameraRelay(control.session_id, control.rate))
        self.online, self.offline_since = None, None

    def on_session_stop(self, session_id: str) -> None:
        if self.served is not None and self.served.control.session_id == session_id:
            self.served = None
        super().on_session_stop(session_id)

    def feed(self, payload: bytes) -> bool:
        """One camera frame message: into the session this robot's tracker serves, if any (False: none, or the
        frame is above the session's admitted rate)."""
        served = self.served
        relayed = None if served is None else served.relay.relay(payload)
        if relayed is None:
            return False
        self.counters.add("received")
        self.inbox.put((keys.key(self.robot, "frames"), relayed))
        if served.relay.status_due:  # as the stack's source counts a camera's frames
            self.report_relayed()
        return True

    def report_relayed(self) -> None:
        """The frames relayed into the session so far, on its status (every few frames, and after the camera's
        last: the gateway then knows them all)."""
        served = self.served
        if served is None:
            return
        status = StatusMsg(session_id=served.control.session_id, robot_id=self.robot, frame_index=-1,
                           stamp=time.time(), service="source", state="relaying",
                           counters={"frames": served.relay.sent})
        self.publish(keys.key(self.robot, "status"), encode(status))

    def handle(self, key: str, payload: bytes) -> None:
        self._watch_link()
        super().handle(key, payload)

    def _watch_link(self) -> None:
        """Say when the server stages go out of reach (the link to the stack, or the stack's replicas): on the
        console at once, and on the session's status once the stack hears the robot again."""
        served = self.served
        online = all(self.replicas[name].alive() for name in self.server_stages)
        if served is None or online == self.online:
            return
        stages = ", ".join(self.server_stages)
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

    def end_sessions(self, timeout: float) -> None:
        """End every session still served here as the gateway's stop would, on the service's own thread (its final
        path goes out), waiting up to ``timeout`` s for them to be handed to the finishing thread."""
        self.served = None
        for session_id in list(self.serving):
            stop = ControlMsg(session_id=session_id, robot_id=self.robot, frame_index=-1, stamp=time.time(),
                              command="stop", tracker=self.replica)
            self.inbox.put((keys.key(self.robot, keys.CONTROL), encode(stop)), urgent=True)
        deadline = time.monotonic() + timeout
        while self.serving and time.monotonic() < deadline:
            time.sleep(0.05)


def run_edge(bus: BusConfig, robot: str, payloads, server_stages: tuple[str, ...], linger_s: float,
             camera: CameraIntrinsics | None = None, say=print) -> int:
    """``twohr camera --edge``: the camera's ``payloads`` into robot ``robot``'s own tracker, in this process, from
    the start of its session (``camera``, where known before the first frame: the networks here are compiled for it
    first). After the last frame it waits up to ``linger_s`` for the session to be stopped (its refined trajectory
    then goes out), and ends any still running itself. Prints what it sent upstream."""
    tracker = EdgeTracker(bus, robot, server_stages)
    tracker.take_priority()  # a frame's pose goes first on the robot too (where it may raise itself)
    stop = threading.Event()
    thread = threading.Thread(target=tracker.run, args=(stop,), name="edge-tracker", daemon=True)
    thread.start()
    if not tracker.ready.wait(30):
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
        while tracker.served is None and thread.is_alive():
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
        while tracker.serving and time.monotonic() < deadline and thread.is_alive():
            time.sleep(0.2)  # the session's stop, from the gateway
    except KeyboardInterrupt:
        elapsed = max(time.monotonic() - t0, 1e-9)
    finally:
        tracker.end_sessions(timeout=30)
        stop.set()
        thread.join(timeout=FINISH_TIMEOUT_S)  # the final bundle adjustment and path of a long session
    sent = tracker.upstream_bytes()
    jobs = {name: replicas.bytes_sent for name, replicas in tracker.replicas.items() if replicas.bytes_sent}
    say(f"tracked {fed} of {frames} frames here in {elapsed:.1f} s ({frames / elapsed:.1f} FPS), {sent} bytes "
        f"({sent / elapsed:.0f} bytes/s upstream): keyframe jobs {jobs or 0}, results {tracker.published_bytes}")
    return 0
