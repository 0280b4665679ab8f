"""The tracker service: publishes each frame's pose on ``twohr/<robot>/pose``, in the session's schedule.

It routes: each session it serves is a :class:`~.session.TrackerSession` (its schedule, health, paths, snapshots,
shared-map keyframes and end), fed every frame of the session's robot. Where the frames and sessions come from is
its :class:`~.inlets.FrameInlet` (the stack's tracker: every robot's frames off the bus, :class:`~.inlets.BusInlet`);
where the networks run is its :class:`~.remote.StageProvider` (the stack's tracker: the detector (``rpc/detect``),
yolo (``rpc/dynamics``) and matcher (``rpc/match``) services, each job to one of their replicas,
:class:`~.remote.RemoteStages`). A robot's own tracker (``twohr camera --edge``) is this service built with its
camera's inlet and its own stages. In the default ``keyframes`` schedule the networks are asked only for keyframes
and every few frames' masks, from worker threads, so a camera's pose never waits for a network (a replay paced by
the poses, rate 0, waits for a late keyframe job as ``twohr run`` does); in ``every_frame`` they are asked for
every frame, in turn.

While the cameras ask more of the per-frame thread than it has, each robot keeps a fair share of it
(:mod:`~.shares`). The end of a session (its final path, and the saving of its map) runs on the service's
finishing thread, never on the per-frame one: a session that stops holds up no other robot's frames.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from twohr import keys
from twohr.errors import TwohrError
from twohr.messages import ControlMsg, FrameMsg, MergeMsg, MessageError, decode, encode
from twohr.rates import RateThinning
from twohr.service import (
    Service,
    UnknownSession,
    bus_from_args,
    change_priority,
    declare_publisher,
    one_line_errors,
    service_parser,
)

from .inlets import BusInlet, FrameInlet
from .maplink import MapLink
from .remote import RemoteStages, StageProvider
from .session import SessionTrack, TrackerSession
from .shares import FairShare, PeerShare

#: robots sharing an overloaded tracker are thinned further while a keyframe job comes back more than this many
#: frames late: a map starved of CPU costs more accuracy than the frames it would take
FAIR_KEYFRAME_LAG = 5
#: beside other trackers, a robot lost for LOST_FRAMES tracked frames in a row is tracked at LOST_HZ until it is found
#: again: its keyframe jobs (relocalisation) need the cores more than its coasting poses; 3 and 5 Hz both held the
#: second robot of the two-robot check under 0.025 m in 7 of 8 runs, without it 0 of 4 (docs/fleet.md, "Fair shares
#: between trackers"); a short loss, which the next keyframe mends, is not thinned
LOST_HZ = 3.0
LOST_FRAMES = 10


class TrackerService(Service):
    """One :class:`~.session.TrackerSession` per session, fed every frame of the session's robot."""

    name = "tracker"
    follows_sessions = True
    follows_moves = True
    priority = "per_frame"  # a frame's pose goes first

    def __init__(self, bus=None, shared_cores: bool = False, snapshots: bool = True, inlet: FrameInlet | None = None,
                 networks: StageProvider | None = None, replica: str | None = None) -> None:
        """``shared_cores``: other trackers run on this host's cores; this one caps its robots' rates so that none is
        served better than the others' worst (:class:`~.shares.PeerShare`), and runs at the networks' priority
        while the others serve live robots (:meth:`_yield_priority`). ``snapshots``: send each live map's snapshot
        to the map room, for the tracker its session moves to if this one dies. ``inlet``: where frames and sessions
        come from (default: every robot's, off the bus); ``networks``: where the stages run (default: the network
        services, over the bus); ``replica``: its replica name (default: the process's)."""
        # robots take turns: on an overloaded stack each gets the same share of the per-frame thread
        super().__init__(bus, queue_size=64, policy="backpressure", fair=True)
        self.replica = replica or self.replica
        self.inlet: FrameInlet = inlet or BusInlet()
        self.networks: StageProvider = networks or RemoteStages()
        self.sessions: dict[str, TrackerSession] = {}  # the sessions this replica serves, by id
        self.maps: MapLink | None = None  # the map room, once the bus session is open
        self.finishing = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tracker-finishing")
        """the ends of sessions, one after another, off the per-frame thread"""
        self.snapshots = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tracker-snapshots") \
            if snapshots else None
        """encodes and sends the maps' snapshots, off the per-frame thread"""
        self._declaring = threading.Lock()  # both threads publish: one publisher per key
        self.published_bytes = 0  # every payload it published so far (a robot's own tracker counts its upstream)
        self.ready = threading.Event()  # serving: its liveliness token and its subscriptions declared
        self.fair = FairShare()  # equal shares of the per-frame thread when the cameras ask for more
        self.peers = PeerShare() if shared_cores else None  # and of the cores, beside other trackers
        self.raised_by = 0  # how far take_priority raised this process (0: it could not, or it is not asked to)
        self.yielding = False  # lowered to the networks' priority while other robots are live on these cores

    def on_start(self) -> None:
        self.networks.open(self.session)
        self.maps = MapLink(self.session, self.publish)

    def process_one(self, timeout: float = 0.2) -> bool:
        self.ready.set()  # the shell's loop runs: the token and the control subscription are declared
        return super().process_one(timeout)

    def take_priority(self) -> None:
        before = os.getpriority(os.PRIO_PROCESS, 0)
        super().take_priority()
        self.raised_by = before - os.getpriority(os.PRIO_PROCESS, 0)

    def _yield_priority(self, others: bool) -> None:
        """Beside other trackers' live robots, back to the networks' priority; alone again, the frames' priority.
        Two trackers raised above the detector, yolo and matcher took the cores their own keyframe jobs needed (the
        second robot's map 0.014-0.032 m in 3 runs, against 0.015-0.021 m in 4 at the networks' priority); a robot
        alone keeps the raise that serves a busy robot's frames first."""
        if self.raised_by and others != self.yielding and change_priority(
                self.raised_by if others else -self.raised_by):
            self.yielding = others

    def robots(self) -> set[str]:
        """The robots whose sessions this tracker serves."""
        return {session.robot_id for session in list(self.sessions.values())}

    def health(self) -> dict:
        """The shell's counters, the robots whose sessions this tracker serves, and the keyframe jobs each network
        replica answered, sent again and lost."""
        return super().health() | {"robots": sorted(self.robots()),
                                   "jobs": {name: r.stats() for name, r in self.networks.replicas.items()}}

    def subscriptions(self) -> list[str]:
        # beside other trackers, every robot's poses too: how well each is served (PeerShare); the map server's
        # merges of the shared maps
        return self.inlet.subscriptions() + [keys.merged_key()] + (
            [keys.all_robots("pose")] if self.peers is not None else [])

    def control_keys(self) -> list[str]:
        return self.inlet.control_keys()

    def takes(self, control: ControlMsg) -> bool:
        return self.inlet.takes(control, self.replica)

    def run(self, stop: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set; sessions still finishing then finish, their final paths and maps sent before
        the bus session closes."""
        super().run(_FinishingFirst(stop or self.stopping, self.finishing))

    def publish(self, key: str, payload: bytes, attachment: str | None = None) -> None:
        """Publish on ``key`` from the per-frame, the finishing or the snapshot thread (or a camera's)."""
        with self._declaring:
            if key not in self._publishers:
                self._publishers[key] = declare_publisher(self.session, key)
            self.published_bytes += len(payload)
        self._publishers[key].put(payload, attachment=attachment)

    def queue_frame(self, key: str, payload: bytes) -> None:
        """A frame message that came another way than the bus (a camera in this process), queued as if it had."""
        self.counters.add("received")
        self.inbox.put((key, payload))

    def on_session_start(self, control: ControlMsg) -> None:
        """A session starts here, or (``move``) comes here from a tracker that died: it goes on in the latest
        snapshot of its map, where the camera is found again, its poses in the same frame as before."""
        if self.inlet.one_session:  # one camera, one session
            for session_id in [s for s in self.sessions if s != control.session_id]:
                self.on_session_stop(session_id)
                self.session_configs.pop(session_id, None)
        stale = self.sessions.pop(control.session_id, None)  # a start repeated: begin again
        if stale is not None and stale.track is not None:
            stale.track.schedule.close()
        self.inlet.started(control)
        session = TrackerSession(control, self, self.maps, self.snapshots)
        session.load(self.replica)
        self.sessions[control.session_id] = session

    def on_session_stop(self, session_id: str) -> None:
        """The session ended: it is handed to the finishing thread (:meth:`_finish`); its frames still coming are
        ignored from now on."""
        self.inlet.stopped(session_id)
        self.fair.forget(session_id)
        session = self.sessions.pop(session_id, None)
        if session is not None and session.track is not None:
            self.finishing.submit(self._finish, session)

    def _finish(self, session: TrackerSession) -> None:
        try:
            session.finish()
        except Exception:  # the thread goes on with the next session
            self.counters.add("errors")
            self.log.exception("session %s: the end of the session failed", session.session_id)

    def end_sessions(self, timeout: float) -> None:
        """End every session still served here as the gateway's stop would, on the service's own thread (its final
        path goes out), waiting up to ``timeout`` s for them to be handed to the finishing thread."""
        for session in list(self.sessions.values()):
            stop = ControlMsg(session_id=session.session_id, robot_id=session.robot_id, frame_index=-1,
                              stamp=time.time(), command="stop", tracker=self.replica)
            self.inbox.put((keys.key(session.robot_id, keys.CONTROL), encode(stop)), urgent=True)
        deadline = time.monotonic() + timeout
        while self.sessions and time.monotonic() < deadline:
            time.sleep(0.05)

    def handle(self, key: str, payload: bytes) -> None:
        """Track one frame now; keyframe and mask work goes to the schedule's workers. In a session paced by the
        camera, a frame that waited too long while newer ones queued is dropped on its header, before any image
        is decoded: fresh data wins (a paced source does not wait for poses, so nothing stalls), but never more
        than ``max_skipped_frames`` in a row, so the optical flow keeps short steps while it catches up."""
        if key.startswith(keys.MAPS_PREFIX):  # the map server merged a robot into a shared map
            merge, _ = decode(payload, MergeMsg)
            if (session := self.sessions.get(merge.session_id)) is not None:
                session.on_merge(merge)
            return
        header, _ = decode(payload, FrameMsg, only=())
        session = self.sessions.get(header.session_id)
        if session is None or session.refused:
            raise UnknownSession(header.session_id)
        try:
            track = session.track_for(header, self.networks)
        except TwohrError as exc:  # a map or vocabulary that does not fit: said once, the session's frames ignored
            session.refused = True
            self.report(header, "error", str(exc))
            return
        pipeline = session.config.pipeline
        waited_ms = (time.time() - header.sent_at) * 1000 if header.sent_at else 0.0
        stale = len(self.inbox) and waited_ms > pipeline.max_frame_age_ms
        if session.paced and (not self._fair_turn(track, header) or (
                stale and track.skipped < pipeline.max_skipped_frames)):
            self.counters.add("dropped")
            session.drop(header)
            return
        session.process(header, payload)
        if session.paced:
            log = track.schedule.keyframe_log
            self.fair.tracked(waited_ms, keyframes_late=bool(log) and log[-1].lag_frames > FAIR_KEYFRAME_LAG)

    def _fair_turn(self, track: SessionTrack, header: FrameMsg) -> bool:
        """Whether this live frame is tracked under the robots' fair shares (:class:`~.shares.FairShare`): while
        the cameras ask more of the per-frame thread than it has, each session keeps an equal rate of evenly spaced
        frames, and the others are dropped on their header. Beside other trackers, also no robot better served than
        theirs (:class:`~.shares.PeerShare`), and a robot lost a while at :data:`LOST_HZ`."""
        self.fair.saw(header.session_id, header.stamp)
        rate = self.fair.rate(header.session_id)
        if self.peers is not None:  # beside other trackers
            served, rates = self.robots(), self.peers.rates()
            self._yield_priority(bool(set(rates) - served))
            cap = self.peers.cap(header.robot_id, served, rates)
            rate = cap if rate is None else rate if cap is None else min(rate, cap)
            if track.lost >= LOST_FRAMES:
                rate = LOST_HZ if rate is None else min(rate, LOST_HZ)
        track.share_hz = rate
        if rate is None:
            track.thinning = None
            return True
        if track.thinning is None:
            track.thinning = RateThinning(rate)
        track.thinning.period = 1.0 / rate
        return track.thinning.keep(header.stamp)

    def _on_sample(self, sample) -> None:
        robot, stream = keys.parse(str(sample.key_expr))
        if self.peers is not None and stream in ("frames", "pose"):
            (self.peers.framed if stream == "frames" else self.peers.posed)(robot)
            if stream == "pose":
                return
        if stream == "frames" and not self.inlet.wants(robot):
            return
        super()._on_sample(sample)
        if stream == keys.CONTROL:  # queued first: a frame that follows it must not overtake it
            self._heard(robot, sample.payload.to_bytes())

    def _heard(self, robot: str, payload: bytes) -> None:
        try:
            control, _ = decode(payload, ControlMsg)
        except MessageError:
            return  # the service thread drops it, and says so
        if control.robot_id == robot:  # else the service thread drops it as spoofed
            self.inlet.heard(control, self.replica)


class _FinishingFirst:
    """The stop event the service shell's loop watches: once ``stop`` is set, the sessions still finishing finish
    first (the shell closes the bus session when its loop ends)."""

    def __init__(self, stop: threading.Event, finishing: ThreadPoolExecutor) -> None:
        self.stop, self.finishing = stop, finishing

    def is_set(self) -> bool:
        if not self.stop.is_set():
            return False
        self.finishing.shutdown(wait=True)
        return True


def main(argv: list[str] | None = None) -> None:
    @one_line_errors("tracker")
    def run() -> None:
        parser = service_parser("tracker", __doc__)
        parser.add_argument("--shared-cores", action="store_true", help="other trackers run on this host's cores "
                            "(twohr up starts one per robot): no robot of this one is served better than theirs, and a "
                            "robot lost a while is tracked at a few Hz while its map finds it again")
        args = parser.parse_args(argv)
        TrackerService(bus_from_args(args), shared_cores=args.shared_cores).run_forever()

    run()
