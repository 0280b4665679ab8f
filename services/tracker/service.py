"""The tracker service: publishes each frame's pose on ``twohr/<robot>/pose``, in the session's schedule.

It feeds every frame of ``frames`` to the session's :class:`~.schedule.Schedule` (built by
:func:`~.schedule.build_schedule`, as ``twohr run`` builds it) over stages that ask the detector
(``rpc/detect``), yolo (``rpc/dynamics``) and matcher (``rpc/match``) services, each job to one of their replicas
(:mod:`twohr.replicas`: the least busy; sent again to another if its replica goes away). In the default ``keyframes``
schedule those are asked only for keyframes and every few frames' masks, from worker threads, so a camera's pose
never waits for a network (a replay paced by the poses, rate 0, waits for a late keyframe job as ``twohr run``
does); in ``every_frame`` they are asked for every frame, in turn.

Live corrections: whenever a keyframe changes the map, the keyframes' poses after bundle adjustment go out on
``twohr/<robot>/path`` (``PathMsg``, ``final`` False): those that are new or moved, the whole path every few
messages (``PathAssembler`` rebuilds it). When a session ends, its refined trajectory of every frame
(final bundle adjustment, re-anchoring, smoothing, as ``twohr run`` writes ``trajectory.txt``) goes out on the same
key with ``final`` True; the gateway serves it as the session's trajectory. That end of a session (and the saving of
its map) runs on the service's finishing thread, never on the per-frame one: a session that stops holds up no other
robot's frames.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from twohr import keys
from twohr.config import PipelineConfig
from twohr.dataset import Frame
from twohr.errors import TwohrError
from twohr.features import Keypoints, Matches
from twohr.geometry import rot_to_quat, transform_points
from twohr.mapfile import MapArrays, MapFile, MapFileError, MapHeader, arrays_file, encode_map, read_map
from twohr.mapmodes import MapMode
from twohr.messages import (
    ControlMsg,
    DynamicsMsg,
    FrameMsg,
    KeyframesMsg,
    KeypointsMsg,
    LandmarksMsg,
    MatchesMsg,
    MatchRequestMsg,
    MergeMsg,
    PathDeltas,
    PathMsg,
    PoseMsg,
    colour_image,
    decode,
    encode,
    path_arrays,
    received_frame,
    split_matches,
)
from twohr.rates import FairShare, PeerShare, RateThinning
from twohr.replicas import Replicas
from twohr.service import (
    Service,
    bus_from_args,
    change_priority,
    declare_publisher,
    one_line_errors,
    service_parser,
)
from twohr.sharing import KeyframeSender
from twohr.trajectory import Trajectory

from .mapfiles import map_file, usable_map
from .schedule import Schedule, build_schedule
from .sharing import SharedFrame
from .stages import FrameStats, Stages, keyframe_job_latency
from .trajectory import TrackResult

#: a live session is ``degraded`` when, over its latest HEALTH_WINDOW frames, more than DEGRADED_DROPPED_PERCENT
#: were dropped, or when its latest keyframe job came back more than DEGRADED_KEYFRAME_LAG frames late
HEALTH_WINDOW = 90
DEGRADED_DROPPED_PERCENT = 10
DEGRADED_KEYFRAME_LAG = 30
#: robots sharing an overloaded tracker are thinned further while a keyframe job comes back more than this many
#: frames late: a map starved of CPU costs more accuracy than the frames it would take
FAIR_KEYFRAME_LAG = 5
#: beside other trackers, a robot lost for LOST_FRAMES tracked frames in a row is tracked at LOST_HZ until it is found
#: again: its keyframe jobs (relocalisation) need the cores more than its coasting poses; 3 and 5 Hz both held the
#: second robot of the two-robot check under 0.025 m in 7 of 8 runs, without it 0 of 4 (docs/fleet.md, "Fair shares
#: between trackers"); a short loss, which the next keyframe mends, is not thinned
LOST_HZ = 3.0
LOST_FRAMES = 10
#: how long the map store may take to hand over or keep a map (seconds)
MAP_TIMEOUT_S = 30.0
#: seconds between the last frame before a camera's stamps went back in time and the first one after
RESTARTED_CLOCK_GAP = 1 / 30
#: a live session's whole map goes to the gateway at most this often (s): the snapshot a session moves with when
#: its tracker dies is at most this old, plus one keyframe job
SNAPSHOT_EVERY_S = 2.0

log = logging.getLogger("twohr.tracker")


class RemoteStage:
    """A network stage in another service, asked over the bus with the frame message as the source sent it: one
    replica of that service answers each job (:class:`twohr.replicas.Replicas`)."""

    def __init__(self, replicas: Replicas, robot_id: str, query: str, parse, timeout: float = 10.0,
                 upload=None) -> None:
        """``upload``: the frame message -> what is sent (default: the message itself)."""
        self.replicas, self.robot_id, self.query, self.parse = replicas, robot_id, query, parse
        self.timeout, self.upload = timeout, upload

    def __call__(self, frame: Frame):
        payload = frame.message if self.upload is None else self.upload(frame.message)
        return self.parse(self.replicas.call(self.robot_id, self.query, payload, self.timeout))


def keypoints_reply(payload: bytes) -> Keypoints:
    _, arrays = decode(payload, KeypointsMsg)
    return Keypoints(arrays["xy"], arrays["descriptors"], arrays["scores"], arrays.get("reliability"),
                     arrays.get("repeatability"))


def _dynamics_reply(payload: bytes) -> tuple[np.ndarray, int]:
    message, arrays = decode(payload, DynamicsMsg, only=("mask",))
    return arrays["mask"].astype(bool), len(message.names)


class RemoteMatcher:
    """The match stage in the matcher service (one replica per job), for the frame it names."""

    def __init__(self, replicas: Replicas, robot_id: str, session_id: str, timeout: float = 10.0) -> None:
        self.replicas, self.robot_id, self.session_id, self.timeout = replicas, robot_id, session_id, timeout

    def __call__(self, frame: Frame, desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
        return self._ask(frame, "local map", {"desc_a": desc_a, "desc_b": desc_b})[0]

    def sets(self, frame: Frame, desc_a: np.ndarray, sets: list[np.ndarray]) -> list[Matches]:
        """Matches against several reference sets (a relocalisation's candidate keyframes) in one query."""
        sizes = np.array([len(desc_b) for desc_b in sets], np.int64)
        return self._ask(frame, "candidate keyframes", {"desc_a": desc_a, "desc_b": np.concatenate(sets),
                                                        "desc_b_sizes": sizes})

    def _ask(self, frame: Frame, reference: str, arrays: dict[str, np.ndarray]) -> list[Matches]:
        request = MatchRequestMsg(session_id=self.session_id, robot_id=self.robot_id, frame_index=frame.index,
                                  stamp=frame.stamp, reference=reference)
        answer = self.replicas.call(self.robot_id, keys.MATCH_QUERY, encode(request, arrays), self.timeout)
        _, found = decode(answer, MatchesMsg)
        return split_matches(Matches(found["idx_a"], found["idx_b"], found["scores"]), found.get("set_counts"))


@dataclass
class SessionHealth:
    """A live session's health over its latest frames: how many were dropped, how late the latest keyframe job came
    back, and the tracker's CPU time per frame (every thread: flow, and the keyframe jobs' mapping)."""

    frames: collections.deque = field(default_factory=lambda: collections.deque(maxlen=HEALTH_WINDOW))
    state: str = "ok"
    cpu_at: float = field(default_factory=time.process_time)
    seen: int = 0  # frames seen, dropped ones included
    reported_at: int = 0  # ``seen`` when the state was last reported

    def add(self, dropped: bool) -> None:
        self.seen += 1
        cpu = time.process_time()
        self.frames.append((dropped, 0.0 if dropped else (cpu - self.cpu_at) * 1000))
        self.cpu_at = cpu

    def verdict(self, keyframe_lag: int, share_hz: float | None = None) -> tuple[str, str, dict[str, int]]:
        """(``ok`` or ``degraded``, why in words, the figures); ``share_hz``: the rate this session's fair share of
        an overloaded tracker allows."""
        dropped = sum(d for d, _ in self.frames)
        tracked = [ms for d, ms in self.frames if not d]
        cpu_ms = float(np.mean(tracked)) if tracked else 0.0
        figures = {"dropped_percent": round(100 * dropped / max(1, len(self.frames))), "keyframe_lag": keyframe_lag,
                   "cpu_ms_per_frame": round(cpu_ms)}
        why = [f"{figures['dropped_percent']} % of the latest {len(self.frames)} frames dropped"
               if figures["dropped_percent"] > DEGRADED_DROPPED_PERCENT else "",
               f"keyframe job {keyframe_lag} frames late" if keyframe_lag > DEGRADED_KEYFRAME_LAG else "",
               f"more robots than the tracker serves at camera rate: each tracked at {share_hz:.0f} Hz"
               if share_hz is not None else ""]
        why = [w for w in why if w]
        detail = "; ".join(why) if why else "keeping up"
        return ("degraded" if why else "ok"), f"{detail} (CPU {cpu_ms:.0f} ms per frame)", figures


@dataclass
class SessionTrack:
    """One session's schedule and what the adapter counts for it."""

    schedule: Schedule
    last_header: FrameMsg
    """the latest frame's header (the session's robot, and the frame a final path is stamped with)"""
    dropped: int = 0  # frames dropped because newer ones were waiting
    skipped: int = 0  # of them, in a row since the last tracked frame
    map_sent: int = -1  # the map version last published on ``landmarks``
    path_deltas: PathDeltas = field(default_factory=PathDeltas)  # the keyframe poses last sent on ``path``
    thinning: RateThinning | None = None  # its frames under a fair share of an overloaded tracker
    share_hz: float | None = None
    health: SessionHealth = field(default_factory=SessionHealth)
    map_name: str = ""  # the session's map: its poses are in this frame ("" = the robot's own)
    lost: int = 0  # frames tracked as lost in a row
    shared: SharedFrame | None = None
    """a session that shares a map: where its poses go (its own frame until the map server places it)"""
    sender: KeyframeSender | None = None
    """a session that shares a map: what the map server has of its map"""
    parent: MapHeader | None = None
    """the header of the map it localizes in or extends, as fetched (the map's next version names it); the file's
    arrays are not kept: the schedule's map was built from them"""
    snapshot_at: float = float("-inf")  # when the map's latest snapshot was sent (monotonic s)
    snapshot_keyframes: int = 0  # keyframes in the map then (or in the map the session started in)
    stamp_shift: float = 0.0  # added to the camera's stamps since they went back in time
    last_stamp: float = float("-inf")

    @property
    def frame_id(self) -> str:
        """The frame its poses are published in: the map's (``''``: the robot's own), or in a shared map
        ``<map>/<robot>`` until the map server placed the robot in the map's."""
        return self.map_name if self.shared is None else self.shared.frame_id

    def session_stamp(self, stamp: float) -> float:
        """The stamp the session uses for a camera stamp: the camera's own, shifted on when it went back in time (a
        replay played again into the session, a camera driver restarted), so that the session's time always goes
        on and its motion model, trajectory and paths stay ordered."""
        shifted = stamp + self.stamp_shift
        if shifted <= self.last_stamp:
            self.stamp_shift += self.last_stamp + RESTARTED_CLOCK_GAP - shifted
            shifted = stamp + self.stamp_shift
            log.warning("session %s: the camera's stamps went back in time; its stamps are shifted by %+.3f s after "
                        "frame %d", self.last_header.session_id, self.stamp_shift, self.last_header.frame_index)
        self.last_stamp = shifted
        return shifted


class TrackerService(Service):
    """One schedule per session, fed every frame of the session's robot; the networks are asked over the bus."""

    name = "tracker"
    follows_sessions = True
    follows_moves = True
    priority = "per_frame"  # a frame's pose goes first

    def __init__(self, bus=None, shared_cores: bool = False, snapshots: bool = True) -> None:
        """``shared_cores``: other trackers run on this host's cores; this one caps its robots' rates so that none is
        served better than the others' worst (:class:`~twohr.rates.PeerShare`), and runs at the networks' priority
        while the others serve live robots (:meth:`_yield_priority`). ``snapshots``: send each live map's snapshot
        to the gateway (:meth:`_keep_snapshot`), for the tracker its session moves to if this one dies."""
        # robots take turns: on an overloaded stack each gets the same share of the per-frame thread
        super().__init__(bus, queue_size=64, policy="backpressure", fair=True)
        self.tracks: dict[str, SessionTrack] = {}
        self.serving: dict[str, str] = {}  # session -> robot, of the sessions this replica serves
        self.elsewhere: dict[str, str] = {}  # session -> robot, of the sessions placed on other tracker replicas
        self.paced: dict[str, bool] = {}
        self.maps: dict[str, ControlMsg] = {}  # sessions with a map, by id: their start (name, mode)
        self.placed: dict[str, np.ndarray] = {}  # sessions placed in a shared map before their first frame
        self.loaded: dict[str, MapFile] = {}  # the maps fetched for them, until their first frame builds the Map
        self.finishing = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tracker-finishing")
        """the ends of sessions, one after another, off the per-frame thread"""
        self.snapshots = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tracker-snapshots") \
            if snapshots else None
        """encodes and sends the maps' snapshots, off the per-frame thread"""
        self._declaring = threading.Lock()  # both threads publish: one publisher per key
        self.replicas: dict[str, Replicas] = {}
        self.fair = FairShare()  # equal shares of the per-frame thread when the cameras ask for more
        self.peers = PeerShare() if shared_cores else None  # and of the cores, beside other trackers
        self.raised_by = 0  # how far take_priority raised this process (0: it could not, or it is not asked to)
        self.yielding = False  # lowered to the networks' priority while other robots are live on these cores

    def on_start(self) -> None:
        self.replicas = {name: Replicas(self.session, name) for name in keys.NETWORK_SERVICES}

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

    def health(self) -> dict:
        """The shell's counters, the robots whose sessions this tracker serves, and the keyframe jobs each network
        replica answered, sent again and lost."""
        robots = sorted(set(list(self.serving.values())))
        return super().health() | {"robots": robots, "jobs": {name: r.stats() for name, r in self.replicas.items()}}

    def subscriptions(self) -> list[str]:
        # beside other trackers, every robot's poses too: how well each is served (PeerShare); the map server's
        # merges of the shared maps
        return [keys.all_robots("frames"), keys.merged_key()] + (
            [keys.all_robots("pose")] if self.peers is not None else [])

    def run(self, stop: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set; sessions still finishing then finish, their final paths and maps sent before
        the bus session closes."""
        super().run(_FinishingFirst(stop or self.stopping, self.finishing))

    def publish(self, key: str, payload: bytes, attachment: str | None = None) -> None:
        """Publish on ``key`` from the per-frame, the finishing or the snapshot thread."""
        with self._declaring:
            if key not in self._publishers:
                self._publishers[key] = declare_publisher(self.session, key)
        self._publishers[key].put(payload, attachment=attachment)

    def on_session_stop(self, session_id: str) -> None:
        """The session ended: it is handed to the finishing thread (:meth:`_finish`); its frames still coming are
        ignored from now on, as its config goes with this stop."""
        self.serving.pop(session_id, None)
        self.paced.pop(session_id, None)
        self.loaded.pop(session_id, None)
        self.placed.pop(session_id, None)
        self.fair.forget(session_id)
        control = self.maps.pop(session_id, None)
        track = self.tracks.pop(session_id, None)
        if track is None:
            return
        self.finishing.submit(self._finish, session_id, track, control, self.session_configs.get(session_id))

    def _finish(self, session_id: str, track: SessionTrack, control: ControlMsg | None,
                config: PipelineConfig | None) -> None:
        """On the finishing thread: the session's refined trajectory (after the keyframe work left, the final bundle
        adjustment, re-anchoring and smoothing, as ``twohr run`` makes it) goes out on ``path`` as the final path;
        then its map is saved where the session builds or extends one."""
        try:
            self._finish_session(session_id, track, control, config)
        except Exception:  # the thread goes on with the next session
            self.counters.add("errors")
            self.log.exception("session %s: the end of the session failed", session_id)

    def _finish_session(self, session_id: str, track: SessionTrack, control: ControlMsg | None,
                        config: PipelineConfig | None) -> None:
        try:
            track.schedule.finish()
            track.schedule.refine()
            refined = track.schedule.trajectory()
        finally:
            track.schedule.close()
        header = track.last_header
        if track.shared is not None:  # its last keyframes first: the map server saves the map once they came
            self._send_keyframes(track, header, track.schedule.map.arrays(), final=True)
            refined = Trajectory(refined.stamps, track.shared.place(refined.poses))
        message = PathMsg(session_id=session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                          stamp=header.stamp, final=True, frame_id=track.frame_id)
        self.publish(keys.key(header.robot_id, "path"), encode(message, path_arrays(refined)))
        latency = keyframe_job_latency(track.schedule.keyframe_log)
        working = track.schedule.map.working_set()
        self.report(header, "keyframe_jobs", f"{latency['count']} keyframe jobs, {working['live_keyframes']} of "
                    f"{working['keyframes']} keyframes in the working set",
                    **{key: round(value) for key, value in latency.items()}, shed=track.schedule.shed_jobs,
                    **{f"map_{key}": value for key, value in working.items()})
        if config is not None and config.loop_closing.vocabulary:
            loops = track.schedule.loop_log
            self.report(header, "loops", f"{loops.closed} loops closed", detected=loops.detected,
                        accepted=loops.accepted, rejected=loops.rejected, closed=loops.closed)
        if control is not None and control.map_mode.saved_by_tracker:  # after the path: it is waited for
            self._save_map(control, track)

    def _track_for(self, header: FrameMsg) -> SessionTrack:
        """The session's schedule, built on its first frame (the camera intrinsics come with the frames), in the
        session's map where it names one to localize in or extend."""
        if header.session_id not in self.tracks:
            config = self.config_for(header.session_id)
            stages = self.stages_for(header, config)
            stored = self.loaded.get(header.session_id)
            world = None if stored is None else usable_map(stored, config, header.camera, f"map {stored.header.name}")
            control = self.maps.get(header.session_id)
            shared = None
            if control is not None and control.map_mode.shared:
                shared = SharedFrame(control.map_name, header.robot_id, self.placed.pop(header.session_id, None))
            self.tracks[header.session_id] = SessionTrack(
                # a replay paced by poses (rate 0) waits for late keyframe jobs as `twohr run` does; a camera does not
                build_schedule(config, header.camera, stages, live=self.paced.get(header.session_id, True),
                               world=world), header,
                map_name=control.map_name if control else "",
                # a snapshot (a moved session's) names no parent: its map's next version names none
                parent=stored.header if stored is not None and (control is None or control.command != "move")
                else None, snapshot_keyframes=0 if world is None else len(world.keyframes), shared=shared,
                # a stored map's keyframes are the map server's already
                sender=None if shared is None else KeyframeSender(0 if world is None else len(world.keyframes)))
            self.loaded.pop(header.session_id, None)  # the session tracks in the Map built from it
        return self.tracks[header.session_id]

    def _fetch_map(self, control: ControlMsg) -> MapFile | None:
        """The map a session localizes in, extends or shares, from the map store over the bus (None: a shared map
        not stored yet)."""
        key = keys.map_key(control.map_name)
        for reply in self.session.get(key, timeout=MAP_TIMEOUT_S):
            if reply.ok is None and control.map_mode.stored_optional:
                return None
            if reply.ok is None:
                raise TwohrError(f"map {control.map_name}: {reply.err.payload.to_bytes().decode(errors='replace')}")
            return read_map(reply.ok.payload.to_bytes(), detector=control.config.detector)
        raise TwohrError(f"map {control.map_name}: the map store did not answer on {key} (twohr up --maps DIR)")

    def stages_for(self, header: FrameMsg, config: PipelineConfig) -> Stages:
        """The stages of a session's schedule: each network asked over the bus, one replica per job."""
        robot_id = header.robot_id
        matcher = RemoteMatcher(self.replicas["matcher"], robot_id, header.session_id)
        # the detector reads the colour image alone: the depth image (half the message) stays here
        return Stages(RemoteStage(self.replicas["detector"], robot_id, keys.DETECT_QUERY, keypoints_reply,
                                  upload=colour_image),
                      RemoteStage(self.replicas["yolo"], robot_id, keys.DYNAMICS_QUERY, _dynamics_reply)
                      if config.yolo.enabled else None, matcher, match_sets=matcher.sets)

    def _save_map(self, control: ControlMsg, track: SessionTrack) -> None:
        """A build or extend session's map, saved in the map store as the map's next version (a map with no keyframe,
        or one that cannot be encoded, is reported and not saved)."""
        if not track.schedule.map:
            self.report(control, "error", f"map {control.map_name} not saved: the session built no map")
            return
        try:
            stored = map_file(track.schedule.map, control.config, control.map_name,
                              built_by=f"session {control.session_id} (robot {control.robot_id})",
                              parent=track.parent)
            payload = encode_map(stored)
        except MapFileError as exc:
            self.report(control, "error", f"map {control.map_name} not saved: {exc}")
            return
        key = keys.map_key(control.map_name, save=True)
        # the session's id goes with the map: the map store records its robot as an owner, and checks its rights
        for reply in self.session.get(key, payload=payload, attachment=control.session_id, timeout=MAP_TIMEOUT_S):
            if reply.ok is not None:
                self.report(control, "map saved", f"map {control.map_name}: {stored.header.keyframes} keyframes, "
                            f"{stored.header.landmarks} landmarks", keyframes=stored.header.keyframes,
                            landmarks=stored.header.landmarks)
            else:
                self.report(control, "error", f"map {control.map_name} not saved: "
                            f"{reply.err.payload.to_bytes().decode(errors='replace')}")
            return
        self.report(control, "error", f"map {control.map_name} not saved: the map store did not answer on {key}")

    def handle(self, key: str, payload: bytes) -> None:
        """Track one frame now; keyframe and mask work goes to the schedule's workers. In a session paced by the
        camera, a frame that waited too long while newer ones queued is dropped on its header, before any image
        is decoded: fresh data wins (a paced source does not wait for poses, so nothing stalls), but never more
        than ``max_skipped_frames`` in a row, so the optical flow keeps short steps while it catches up."""
        if key.startswith(keys.MAPS_PREFIX):
            self._on_merge(payload)
            return
        header, _ = decode(payload, FrameMsg, only=())
        config = self.config_for(header.session_id)
        try:
            track = self._track_for(header)
        except TwohrError as exc:  # a map or vocabulary that does not fit: said once, the session's frames ignored
            self.session_configs.pop(header.session_id, None)
            self.report(header, "error", str(exc))
            return
        waited_ms = (time.time() - header.sent_at) * 1000 if header.sent_at else 0.0
        stale = len(self.inbox) and waited_ms > config.pipeline.max_frame_age_ms
        paced = self.paced.get(header.session_id)
        if paced and (not self._fair_turn(track, header) or (
                stale and track.skipped < config.pipeline.max_skipped_frames)):
            self.counters.add("dropped")
            track.dropped += 1
            track.skipped += 1
            track.health.add(dropped=True)
            self._report_health(track, header)
            return
        track.skipped = 0
        _, frame = received_frame(payload)
        frame.stamp = track.session_stamp(header.stamp)
        header = header.model_copy(update={"stamp": frame.stamp})
        track.last_header = header
        result, stats = track.schedule.process(frame)
        track.lost = track.lost + 1 if result.status == "lost" else 0
        if paced:
            log = track.schedule.keyframe_log
            self.fair.tracked(waited_ms, keyframes_late=bool(log) and log[-1].lag_frames > FAIR_KEYFRAME_LAG)
        track.health.add(dropped=False)
        if result.posed:
            self._publish_pose(header, result, stats, track)
        else:  # no pose before the camera is found in the map: the frame is answered on the session's status
            self.report(header, "relocalising", f"looking for the camera in map {track.map_name}",
                        frame=header.frame_index)
        self._publish_map(track, header)
        self._keep_snapshot(track, header)
        self._report_health(track, header)

    def _fair_turn(self, track: SessionTrack, header: FrameMsg) -> bool:
        """Whether this live frame is tracked under the robots' fair shares (:class:`~twohr.rates.FairShare`):
        while the cameras ask more of the per-frame thread than it has, each session keeps an equal rate of evenly
        spaced frames, and the others are dropped on their header. Beside other trackers, also no robot better
        served than theirs (:class:`~twohr.rates.PeerShare`), and a robot lost a while at :data:`LOST_HZ`."""
        self.fair.saw(header.session_id, header.stamp)
        rate = self.fair.rate(header.session_id)
        if self.peers is not None:  # beside other trackers
            served, rates = set(self.serving.values()), self.peers.rates()
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

    def _report_health(self, track: SessionTrack, header: FrameMsg) -> None:
        """``degraded`` (and why) or ``ok`` on the session's status, when it changes and every window while
        degraded."""
        log = track.schedule.keyframe_log
        state, detail, figures = track.health.verdict(log[-1].lag_frames if log else 0, track.share_hz)
        health = track.health
        if state == health.state and (state == "ok" or health.seen - health.reported_at < HEALTH_WINDOW):
            return
        health.state, health.reported_at = state, health.seen
        self.report(header, state, detail, **figures)

    def _publish_map(self, track: SessionTrack, header: FrameMsg) -> None:
        """Whenever a keyframe has changed the map: its points on ``landmarks``, and the keyframes' poses after
        bundle adjustment on ``path`` (a live correction: the robot's earlier poses move with their keyframe), as
        a delta of the keyframes that are new or moved, the full path every few messages (:class:`PathDeltas`)."""
        snapshot = track.schedule.map_snapshot(since=track.map_sent)
        if snapshot is None:
            return
        track.map_sent = snapshot.version
        ids = dict(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                   stamp=header.stamp)
        points, poses = snapshot.points, snapshot.keyframe_poses
        if track.shared is not None:
            points, poses = transform_points(track.shared.place(np.eye(4)), points), track.shared.place(poses)
        if len(points):
            self.publish(keys.key(header.robot_id, "landmarks"),
                         encode(LandmarksMsg(**ids), {"points": points.astype(np.float32)}))
        fields, arrays = track.path_deltas.next(Trajectory(snapshot.keyframe_stamps, poses))
        path = PathMsg(**ids, final=False, frame_id=track.frame_id, **fields)
        self.publish(keys.key(header.robot_id, "path"), encode(path, arrays))

    def _keep_snapshot(self, track: SessionTrack, header: FrameMsg) -> None:
        """Every :data:`SNAPSHOT_EVERY_S` while it gains keyframes, a copy of the session's whole map goes to the
        gateway on ``twohr/<robot>/map/snapshot`` as a map file (encoded and sent on the snapshot thread): where this
        process dies, the tracker the session moves to starts from it (:meth:`_fetch_snapshot`)."""
        now = time.monotonic()
        due = self.snapshots is not None and now - track.snapshot_at >= SNAPSHOT_EVERY_S and (
            len(track.schedule.map.keyframes) > track.snapshot_keyframes)
        if not due and track.sender is None:
            return  # a map that gained no keyframe is sent no more (a stored one is in the map store already)
        arrays = track.schedule.map_copy()  # a session that shares its map asks for a copy after every job
        if arrays is None:
            return
        if track.sender is not None:
            self._send_keyframes(track, header, arrays)
        if not due:
            return
        track.snapshot_at, track.snapshot_keyframes = now, len(arrays.keyframe_stamps)
        self.snapshots.submit(self._send_snapshot, arrays, track, header, self.config_for(header.session_id))

    def _send_snapshot(self, arrays: MapArrays, track: SessionTrack, header: FrameMsg, config: PipelineConfig) -> None:
        try:
            stored = arrays_file(arrays, header.camera, config, track.map_name or "snapshot",
                                 built_by=f"session {header.session_id} (robot {header.robot_id}), a snapshot")
            self.publish(keys.snapshot_key(header.robot_id), encode_map(stored), attachment=header.session_id)
        except Exception:  # the session goes on without this snapshot
            self.counters.add("errors")
            self.log.exception("session %s: the map's snapshot was not sent", header.session_id)

    def _fetch_snapshot(self, control: ControlMsg) -> MapFile | None:
        """The latest snapshot of a session's map (a session moved here from a tracker that died), from the
        gateway; None where it holds none (the session had no map yet) or it is unusable: the session starts a new
        map then."""
        key = keys.snapshot_key(control.robot_id)
        for reply in self.session.get(key, attachment=control.session_id, timeout=MAP_TIMEOUT_S):
            if reply.ok is None:
                self.log.warning("session %s: no map snapshot: %s", control.session_id,
                                 reply.err.payload.to_bytes().decode(errors="replace"))
                return None
            try:
                return read_map(reply.ok.payload.to_bytes(), detector=control.config.detector)
            except MapFileError as exc:
                self.log.warning("session %s: its map snapshot is unusable: %s", control.session_id, exc)
                return None
        return None

    def _send_keyframes(self, track: SessionTrack, header: FrameMsg, arrays: MapArrays, final: bool = False) -> None:
        """The keyframes of a shared map's session that the map server has not had yet (``final``: the session's
        last message, its keyframes as the final bundle adjustment left them)."""
        batch = track.sender.next(arrays, final=final)
        if batch is None:
            return
        first, blobs = batch
        message = KeyframesMsg(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                               stamp=header.stamp, map_name=track.shared.map_name, first=first, camera=header.camera,
                               final=final)
        payload = encode(message, blobs)
        track.sender.bytes_sent += len(payload)
        self.publish(keys.key(header.robot_id, "keyframes"), payload)

    def _on_merge(self, payload: bytes) -> None:
        """The map server placed a robot in a shared map's frame: a session of this tracker's puts its poses there
        from now on, and sends its path again at once, every keyframe moved (its earlier poses with them)."""
        merge, _ = decode(payload, MergeMsg)
        control = self.maps.get(merge.session_id)
        if control is None or not control.map_mode.shared or control.map_name != merge.map_name:
            return  # not a session of this tracker's
        T = merge.transform
        track = self.tracks.get(merge.session_id)
        if track is None:  # placed before its first frame: its schedule starts placed
            self.placed[merge.session_id] = T
            return
        track.shared.T = T
        track.path_deltas = PathDeltas()  # the next path message is whole
        track.map_sent = -1
        self._publish_map(track, track.last_header)

    def _publish_pose(self, header: FrameMsg, result: TrackResult, stats: FrameStats, track: SessionTrack) -> None:
        placed = result.pose if track.shared is None else track.shared.place(result.pose)
        pose = PoseMsg(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                       stamp=header.stamp, frame_id=track.frame_id, position=placed[:3, 3].tolist(),
                       orientation=rot_to_quat(placed[:3, :3]).tolist(), status=result.status,
                       num_keypoints=stats.keypoints, num_matches=result.num_matches, num_inliers=result.num_inliers,
                       is_keyframe=result.is_keyframe, frame_sent_at=header.sent_at,
                       elapsed_ms={"detector": stats.ms_detector, "yolo": stats.ms_yolo, "tracker": stats.ms_tracker})
        self.publish(keys.key(header.robot_id, "pose"), encode(pose))

    def takes(self, control: ControlMsg) -> bool:
        """A session placed on another tracker replica is that one's: its robot's frames are not even queued here
        while it runs (:meth:`_on_sample`)."""
        if control.tracker in ("", self.replica):
            return True
        if control.command in ("start", "move"):
            self.elsewhere[control.session_id] = control.robot_id
        else:
            self.elsewhere.pop(control.session_id, None)
        return False

    def _on_sample(self, sample) -> None:
        robot, stream = keys.parse(str(sample.key_expr))
        if self.peers is not None and stream in ("frames", "pose"):
            (self.peers.framed if stream == "frames" else self.peers.posed)(robot)
            if stream == "pose":
                return
        if stream == "frames" and robot in self.elsewhere.values() and robot not in self.serving.values():
            return  # a robot another tracker serves (its controls still come in: they move it)
        super()._on_sample(sample)

    def on_session_start(self, control: ControlMsg) -> None:
        """A session starts here, or (``move``) comes here from a tracker that died: it goes on in the latest
        snapshot of its map, where the camera is found again, its poses in the same frame as before."""
        self.serving[control.session_id] = control.robot_id
        self.elsewhere.pop(control.session_id, None)
        stale = self.tracks.pop(control.session_id, None)  # a start repeated: begin again
        if stale is not None:
            stale.schedule.close()
        if control.map_mode is not MapMode.NONE:
            self.maps[control.session_id] = control
        if control.command == "move":
            snapshot = self._fetch_snapshot(control)
            if snapshot is None and control.map_mode.resumes_in_stored:  # it had not grown: the stored map
                snapshot = self._fetch_map(control)
            if snapshot is not None:
                self.loaded[control.session_id] = snapshot
            self.report(control, "moved", f"tracker {self.replica} serves the session now, " + (
                f"in its map as last kept ({snapshot.header.keyframes} keyframes)" if snapshot is not None else
                "in a new map: no snapshot of its map was kept (its poses are in a new frame)"))
        elif control.map_mode.reads_stored:
            stored = self._fetch_map(control)
            if stored is not None:
                self.loaded[control.session_id] = stored
                if control.map_mode.shared:  # a stored shared map: its frame is the robot's from the start
                    self.placed[control.session_id] = np.eye(4)
        # paced by the camera (a real-rate replay or a live camera): the source never waits for poses
        self.paced[control.session_id] = control.rate > 0 or not control.sequence


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
