"""One session a tracker service serves, as an object (:class:`TrackerSession`): from its start (the map or snapshot
it starts in) through its frames (its schedule and health, :class:`SessionTrack`; its poses, paths and landmarks;
its map's snapshots; in a shared map, its keyframes to the map server and the merge that puts it in the map's
frame) to its end (the final path, the map saved). The service routes to it; it publishes through the service
(:class:`Outlet`) and reaches the map room (the map store and the snapshots) through a :class:`~.maplink.MapLink`.

Live corrections: whenever a keyframe changes the map, the keyframes' poses after bundle adjustment go out on
``twohr/<robot>/path`` (``PathMsg``, ``final`` False): those that are new or moved, the whole path every few
messages (``PathAssembler`` rebuilds it). When a session ends, its refined trajectory of every frame (final bundle
adjustment, re-anchoring, smoothing, as ``twohr run`` writes ``trajectory.txt``) goes out on the same key with
``final`` True; the gateway serves it as the session's trajectory.
"""

from __future__ import annotations

import collections
import logging
import time
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from twohr import keys
from twohr.config import PipelineConfig
from twohr.errors import TwohrError
from twohr.geometry import rot_to_quat, transform_points
from twohr.keyframe_sender import KeyframeSender
from twohr.mapfile import MapArrays, MapFile, MapHeader, arrays_file
from twohr.mapmodes import MapMode
from twohr.messages import (
    ControlMsg,
    FrameMsg,
    KeyframesMsg,
    LandmarksMsg,
    MergeMsg,
    PathDeltas,
    PathMsg,
    PoseMsg,
    encode,
    path_arrays,
    received_frame,
)
from twohr.rates import RateThinning
from twohr.service import Counters
from twohr.trajectory import Trajectory

from .mapfiles import map_file, usable_map
from .maplink import MapLink
from .remote import StageProvider
from .schedule import Schedule, build_schedule
from .shared_map_frame import SharedMapFrame
from .stages import FrameStats, keyframe_job_latency
from .trajectory import TrackResult

#: a live session is ``degraded`` when, over its latest HEALTH_WINDOW frames, more than DEGRADED_DROPPED_PERCENT
#: were dropped, or when its latest keyframe job came back more than DEGRADED_KEYFRAME_LAG frames late
HEALTH_WINDOW = 90
DEGRADED_DROPPED_PERCENT = 10
DEGRADED_KEYFRAME_LAG = 30
#: seconds between the last frame before a camera's stamps went back in time and the first one after
RESTARTED_CLOCK_GAP = 1 / 30
#: a live session's whole map goes to the map room at most this often (s): the snapshot a session moves with when
#: its tracker dies is at most this old, plus one keyframe job
SNAPSHOT_EVERY_S = 2.0

log = logging.getLogger("twohr.tracker")


class Outlet(Protocol):
    """What a session sends through its tracker service (from the per-frame, finishing and snapshot threads)."""

    counters: Counters

    def publish(self, key: str, payload: bytes, attachment: str | None = None) -> None: ...

    def report(self, about, state: str, detail: str = "", **counters: int) -> None: ...


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
    """A session's schedule, from its first frame, and what the per-frame thread counts for it."""

    schedule: Schedule
    last_header: FrameMsg
    """the latest frame's header (the session's robot, and the frame a final path is stamped with)"""
    dropped: int = 0  # frames dropped because newer ones were waiting
    skipped: int = 0  # of them, in a row since the last tracked frame
    thinning: RateThinning | None = None  # its frames under a fair share of an overloaded tracker
    share_hz: float | None = None
    health: SessionHealth = field(default_factory=SessionHealth)
    lost: int = 0  # frames tracked as lost in a row
    stamp_shift: float = 0.0  # added to the camera's stamps since they went back in time
    last_stamp: float = float("-inf")

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


class TrackerSession:
    """One session a tracker serves: ``control``, its start (or ``move``); ``outlet``, the service it publishes
    through; ``maps``, the map room; ``snapshots``, the thread that sends its map's snapshots (None: none sent)."""

    def __init__(self, control: ControlMsg, outlet: Outlet, maps: MapLink, snapshots: Executor | None) -> None:
        self.control, self.outlet, self.maps, self.snapshots = control, outlet, maps, snapshots
        # paced by the camera (a real-rate replay or a live camera): the source never waits for poses
        self.paced = control.rate > 0 or not control.sequence
        self.refused = False  # its map or vocabulary did not fit: said once, its frames ignored
        self.stored: MapFile | None = None  # the map fetched for it, until its first frame builds the Map
        self.T_map_robot: np.ndarray | None = None
        """a shared map's session in the map's frame before its first frame (its map was stored, or the map server
        merged it early): the robot's frame into the map's, until :attr:`map_frame` holds it"""
        self.track: SessionTrack | None = None
        self.map_frame: SharedMapFrame | None = None
        """a session that shares a map: where its poses go (its own frame until the map server merges it)"""
        self.sender: KeyframeSender | None = None
        """a session that shares a map: what the map server has of its map"""
        self.parent: MapHeader | None = None
        """the header of the map it localizes in or extends, as fetched (the map's next version names it); the file's
        arrays are not kept: the schedule's map was built from them"""
        self.map_sent = -1  # the map version last published on ``landmarks``
        self.map_keyframes = 0  # keyframes in the map as last published (as the per-frame path has it)
        self.path_deltas = PathDeltas()  # the keyframe poses last sent on ``path``
        self.snapshot_at = float("-inf")  # when the map's latest snapshot was sent (monotonic s)
        self.snapshot_keyframes = 0  # keyframes in the map then (or in the map the session started in)

    @property
    def session_id(self) -> str:
        return self.control.session_id

    @property
    def robot_id(self) -> str:
        return self.control.robot_id

    @property
    def config(self) -> PipelineConfig:
        return self.control.config

    @property
    def map_name(self) -> str:
        """The session's map: its poses are in this frame (``''``: the robot's own)."""
        return self.control.map_name if self.control.map_mode is not MapMode.NONE else ""

    @property
    def frame_id(self) -> str:
        """The frame its poses are published in: the map's (``''``: the robot's own), or in a shared map
        ``<map>/<robot>`` until the map server merged the robot into the map's."""
        return self.map_name if self.map_frame is None else self.map_frame.frame_id

    def load(self, replica: str) -> None:
        """Fetch the map it starts in: a moved session's latest snapshot (else, where it had not grown, its stored
        map), or the stored map it localizes in, extends or shares; :class:`TwohrError` where that fails."""
        control = self.control
        if control.command == "move":
            snapshot = self.maps.fetch_snapshot(control)
            if snapshot is None and control.map_mode.resumes_in_stored:  # it had not grown: the stored map
                snapshot = self.maps.fetch(control)
            self.stored = snapshot
            self.outlet.report(control, "moved", f"tracker {replica} serves the session now, " + (
                f"in its map as last kept ({snapshot.header.keyframes} keyframes)" if snapshot is not None else
                "in a new map: no snapshot of its map was kept (its poses are in a new frame)"))
        elif control.map_mode.reads_stored:
            self.stored = self.maps.fetch(control)
            if self.stored is not None and control.map_mode.shared:  # a stored shared map: the robot's frame at once
                self.T_map_robot = np.eye(4)

    def track_for(self, header: FrameMsg, networks: StageProvider) -> SessionTrack:
        """Its schedule, built on its first frame (the camera intrinsics come with the frames), in the map it was
        started in, if any; :class:`TwohrError` where that map or the config's vocabulary does not fit."""
        if self.track is not None:
            return self.track
        config, stored = self.config, self.stored
        stages = networks.stages_for(header, config)
        world = None if stored is None else usable_map(stored, config, header.camera, f"map {stored.header.name}")
        known = 0 if world is None else len(world.keyframes)
        if self.control.map_mode.shared:
            self.map_frame = SharedMapFrame(self.control.map_name, header.robot_id, self.T_map_robot)
            self.sender = KeyframeSender(known)  # a stored map's keyframes are the map server's already
        # a snapshot (a moved session's) names no parent: its map's next version names none
        self.parent = stored.header if stored is not None and self.control.command != "move" else None
        self.snapshot_keyframes = known
        # a replay paced by poses (rate 0) waits for late keyframe jobs as `twohr run` does; a camera does not
        self.track = SessionTrack(build_schedule(config, header.camera, stages, live=self.paced, world=world), header)
        self.stored, self.T_map_robot = None, None  # the session tracks in the Map built from it
        return self.track

    def drop(self, header: FrameMsg) -> None:
        """A frame dropped on its header (stale, or above the session's fair share)."""
        track = self.track
        track.dropped += 1
        track.skipped += 1
        track.health.add(dropped=True)
        self.report_health(header)

    def process(self, header: FrameMsg, payload: bytes) -> None:
        """Track one frame; publish its pose (or that the camera is still looked for in the map), the map where a
        keyframe changed it, its snapshot when one is due, and the session's health when it changes."""
        track = self.track
        track.skipped = 0
        _, frame = received_frame(payload)
        frame.stamp = track.session_stamp(header.stamp)
        header = header.model_copy(update={"stamp": frame.stamp})
        track.last_header = header
        result, stats = track.schedule.process(frame)
        track.lost = track.lost + 1 if result.status == "lost" else 0
        track.health.add(dropped=False)
        if result.posed:
            self.publish_pose(header, result, stats)
        else:  # no pose before the camera is found in the map: the frame is answered on the session's status
            self.outlet.report(header, "relocalising", f"looking for the camera in map {self.map_name}",
                               frame=header.frame_index)
        self.publish_map(header)
        self.keep_snapshot(header)
        self.report_health(header)

    def report_health(self, header: FrameMsg) -> None:
        """``degraded`` (and why) or ``ok`` on the session's status, when it changes and every window while
        degraded."""
        track = self.track
        log = track.schedule.keyframe_log
        state, detail, figures = track.health.verdict(log[-1].lag_frames if log else 0, track.share_hz)
        health = track.health
        if state == health.state and (state == "ok" or health.seen - health.reported_at < HEALTH_WINDOW):
            return
        health.state, health.reported_at = state, health.seen
        self.outlet.report(header, state, detail, **figures)

    def publish_pose(self, header: FrameMsg, result: TrackResult, stats: FrameStats) -> None:
        in_frame = result.pose if self.map_frame is None else self.map_frame.place(result.pose)
        pose = PoseMsg(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                       stamp=header.stamp, frame_id=self.frame_id, position=in_frame[:3, 3].tolist(),
                       orientation=rot_to_quat(in_frame[:3, :3]).tolist(), status=result.status,
                       num_keypoints=stats.keypoints, num_matches=result.num_matches, num_inliers=result.num_inliers,
                       is_keyframe=result.is_keyframe, frame_sent_at=header.sent_at,
                       elapsed_ms={"detector": stats.ms_detector, "yolo": stats.ms_yolo, "tracker": stats.ms_tracker})
        self.outlet.publish(keys.key(header.robot_id, "pose"), encode(pose))

    def publish_map(self, header: FrameMsg) -> None:
        """Whenever a keyframe has changed the map: its points on ``landmarks``, and the keyframes' poses after
        bundle adjustment on ``path`` (a live correction: the robot's earlier poses move with their keyframe), as
        a delta of the keyframes that are new or moved, the full path every few messages (:class:`PathDeltas`)."""
        snapshot = self.track.schedule.map_snapshot(since=self.map_sent)
        if snapshot is None:
            return
        self.map_sent, self.map_keyframes = snapshot.version, len(snapshot.keyframe_stamps)
        ids = dict(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                   stamp=header.stamp)
        points, poses = snapshot.points, snapshot.keyframe_poses
        if self.map_frame is not None:
            points, poses = transform_points(self.map_frame.place(np.eye(4)), points), self.map_frame.place(poses)
        if len(points):
            self.outlet.publish(keys.key(header.robot_id, "landmarks"),
                                encode(LandmarksMsg(**ids), {"points": points.astype(np.float32)}))
        fields, arrays = self.path_deltas.next(Trajectory(snapshot.keyframe_stamps, poses))
        path = PathMsg(**ids, final=False, frame_id=self.frame_id, **fields)
        self.outlet.publish(keys.key(header.robot_id, "path"), encode(path, arrays))

    def keep_snapshot(self, header: FrameMsg) -> None:
        """Every :data:`SNAPSHOT_EVERY_S` while it gains keyframes, a copy of the session's whole map goes to the
        map room on ``twohr/<robot>/map/snapshot`` as a map file (encoded and sent on the snapshot thread): where this
        process dies, the tracker the session moves to starts from it (:meth:`MapLink.fetch_snapshot`). The map's
        keyframes are counted as last published: the schedule's map is not read while frames flow."""
        now = time.monotonic()
        due = self.snapshots is not None and now - self.snapshot_at >= SNAPSHOT_EVERY_S and (
            self.map_keyframes > self.snapshot_keyframes)
        if not due and self.sender is None:
            return  # a map that gained no keyframe is sent no more (a stored one is in the map store already)
        arrays = self.track.schedule.map_copy()  # a session that shares its map asks for a copy after every job
        if arrays is None:
            return
        if self.sender is not None:
            self.send_keyframes(header, arrays)
        if not due:
            return
        self.snapshot_at, self.snapshot_keyframes = now, len(arrays.keyframe_stamps)
        self.snapshots.submit(self._send_snapshot, arrays, header)

    def _send_snapshot(self, arrays: MapArrays, header: FrameMsg) -> None:
        try:
            stored = arrays_file(arrays, header.camera, self.config, self.map_name or "snapshot",
                                 built_by=f"session {header.session_id} (robot {header.robot_id}), a snapshot")
            self.maps.send_snapshot(header.robot_id, header.session_id, stored)
        except Exception:  # the session goes on without this snapshot
            self.outlet.counters.add("errors")
            log.exception("session %s: the map's snapshot was not sent", header.session_id)

    def send_keyframes(self, header: FrameMsg, arrays: MapArrays, final: bool = False) -> None:
        """The keyframes of a shared map's session that the map server has not had yet (``final``: the session's
        last message, its keyframes as the final bundle adjustment left them)."""
        batch = self.sender.next(arrays, final=final)
        if batch is None:
            return
        first, blobs = batch
        message = KeyframesMsg(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                               stamp=header.stamp, map_name=self.map_frame.map_name, first=first, camera=header.camera,
                               final=final)
        payload = encode(message, blobs)
        self.sender.bytes_sent += len(payload)
        self.outlet.publish(keys.key(header.robot_id, "keyframes"), payload)

    def on_merge(self, merge: MergeMsg) -> None:
        """The map server merged a robot into a shared map's frame: the session puts its poses there from now on, and
        sends its path again at once, every keyframe moved (its earlier poses with them)."""
        if not self.control.map_mode.shared or self.control.map_name != merge.map_name:
            return  # not this session's map
        if self.track is None:  # merged before its first frame: its schedule starts in the map's frame
            self.T_map_robot = merge.transform
            return
        self.map_frame.T = merge.transform
        self.path_deltas = PathDeltas()  # the next path message is whole
        self.map_sent = -1
        self.publish_map(self.track.last_header)

    def finish(self) -> None:
        """On the service's finishing thread: the session's refined trajectory (after the keyframe work left, the
        final bundle adjustment, re-anchoring and smoothing, as ``twohr run`` makes it) goes out on ``path`` as the
        final path; then its map is saved where the session builds or extends one."""
        track = self.track
        try:
            track.schedule.finish()
            track.schedule.refine()
            refined = track.schedule.trajectory()
        finally:
            track.schedule.close()
        header = track.last_header
        if self.map_frame is not None:  # its last keyframes first: the map server saves the map once they came
            self.send_keyframes(header, track.schedule.map.arrays(), final=True)
            refined = Trajectory(refined.stamps, self.map_frame.place(refined.poses))
        message = PathMsg(session_id=self.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                          stamp=header.stamp, final=True, frame_id=self.frame_id)
        self.outlet.publish(keys.key(header.robot_id, "path"), encode(message, path_arrays(refined)))
        latency = keyframe_job_latency(track.schedule.keyframe_log)
        working = track.schedule.map.working_set()
        self.outlet.report(header, "keyframe_jobs", f"{latency['count']} keyframe jobs, {working['live_keyframes']} "
                           f"of {working['keyframes']} keyframes in the working set",
                           **{key: round(value) for key, value in latency.items()}, shed=track.schedule.shed_jobs,
                           **{f"map_{key}": value for key, value in working.items()})
        if self.config.loop_closing.vocabulary:
            loops = track.schedule.loop_log
            self.outlet.report(header, "loops", f"{loops.closed} loops closed", detected=loops.detected,
                               accepted=loops.accepted, rejected=loops.rejected, closed=loops.closed)
        if self.control.map_mode.saved_by_tracker:  # after the path: it is waited for
            self._save_map()

    def _save_map(self) -> None:
        """A build or extend session's map, saved in the map store as the map's next version (a map with no keyframe,
        or one that cannot be encoded, is reported and not saved)."""
        control, world = self.control, self.track.schedule.map
        if not world:
            self.outlet.report(control, "error", f"map {control.map_name} not saved: the session built no map")
            return
        try:
            stored = map_file(world, control.config, control.map_name,
                              built_by=f"session {control.session_id} (robot {control.robot_id})", parent=self.parent)
            self.maps.save(control, stored)
        except TwohrError as exc:
            self.outlet.report(control, "error", f"map {control.map_name} not saved: {exc}")
            return
        self.outlet.report(control, "map saved", f"map {control.map_name}: {stored.header.keyframes} keyframes, "
                           f"{stored.header.landmarks} landmarks", keyframes=stored.header.keyframes,
                           landmarks=stored.header.landmarks)
