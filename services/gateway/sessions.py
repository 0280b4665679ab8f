"""Session bookkeeping for the gateway: what was asked, what the bus has reported since. No HTTP, no Zenoh."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field, model_validator

from twohr.config import PipelineConfig
from twohr.geometry import invert_pose, make_pose, quat_to_rot, rot_to_quat
from twohr.ids import check_robot_id
from twohr.mapfile import OPERATOR
from twohr.mapmodes import MapRequest
from twohr.messages import ID_PATTERN, MergeMsg, PathMsg, PoseMsg, StatusMsg
from twohr.trajectory import Trajectory

SessionState = Literal["starting", "running", "finished", "stopped", "failed"]
ACTIVE = ("starting", "running")
MAX_FRAMES = 10_000_000


class SessionRequest(BaseModel):
    """Body of ``POST /sessions``: a replay of a recorded sequence, or a live camera session."""

    source: Literal["sequence", "camera"] = Field(
        "sequence", description="'sequence': replay `sequence` from a data root; 'camera': track the frames a "
        "camera driver publishes on twohr/<robot_id>/camera (e.g. `twohr camera`) until DELETE")
    sequence: str | None = Field(None, min_length=1, max_length=1024,
                                 description="sequence folder, relative to a data root or absolute inside one "
                                 "(source 'sequence' only)")
    robot_id: str = Field("robot1", pattern=ID_PATTERN)
    rate: float = Field(0.0, ge=0, le=100, description="a replay: its speed, 1 = real time, 0 = as fast as the "
                        "pipeline keeps up; a camera session: the frames per second the stack tracks for this robot "
                        "(e.g. 15 to be admitted at half a 30 Hz camera's share; the source relays every other "
                        "frame), 0 = every frame the camera sends")
    record: bool = Field(True, description="write every stream to an MCAP file")
    record_descriptors: bool = Field(False, description="keep the raw keypoint descriptors in the recording (large)")
    record_frames: bool = Field(False, description="keep the raw RGB-D frames in the recording, for exact replay")
    max_frames: int | None = Field(None, ge=1, le=MAX_FRAMES, description="stop after this many frames")
    start: int = Field(0, ge=0, le=MAX_FRAMES, description="a replay's first frame (source 'sequence' only)")
    map: MapRequest | None = Field(None, description="a map from the map store (twohr up --maps DIR)")
    config: dict[str, Any] = Field(
        default_factory=dict, description="pipeline config overrides, nested or dotted: {'detector.max_keypoints': 800}"
    )

    model_config = {"extra": "forbid"}

    @model_validator(mode="after")
    def _sequence_matches_source(self) -> SessionRequest:
        check_robot_id(self.robot_id)  # the pattern holds: this refuses a reserved name
        if self.source == "sequence" and self.sequence is None:
            raise ValueError("give a sequence, or \"source\": \"camera\" for a live camera session")
        if self.source == "camera" and self.sequence is not None:
            raise ValueError("a camera session takes no sequence")
        if self.source == "camera" and self.start:
            raise ValueError("a camera session takes no start frame")
        return self


class PoseOut(BaseModel):
    frame_index: int
    stamp: float
    position: list[float]
    orientation: list[float]
    status: str


class MergeOut(BaseModel):
    """A robot placed in a shared map's frame (``twohr/maps/<name>/merged``)."""

    kind: Literal["defines", "joined", "merged"] = Field(
        description="merged: its places were found in the map; defines: its frame is the map's; joined: it tracks "
        "in the stored map")
    frame_id: str = Field(description="the map's frame, its poses' from then on")
    at: float = Field(description="wall-clock time of the merge")
    into: list[str] = Field(default_factory=list, description="the robots it was found among")
    inliers: list[int] = Field(default_factory=list, description="the inliers of each agreeing match")
    keyframes: int = Field(0, description="the robot's keyframes when it was merged")
    refinements: int = Field(0, description="times its transform was refined since, later matches averaged in "
                             "(position, orientation and inliers are the latest)")
    ms: float = Field(0.0, description="the map server's time for the search that merged it")
    position: list[float] = Field(description="the transform of the robot's own frame into the map's")
    orientation: list[float]


class SessionInfo(BaseModel):
    """What ``GET /sessions/{id}`` returns."""

    id: str
    robot_id: str
    source: Literal["sequence", "camera"] = "sequence"
    sequence: str | None = None
    state: SessionState = Field(description="starting, running, then finished, stopped (DELETE) or failed "
                                "(detail says why: a service rejected the config, stopped, or the pipeline stalled)")
    detail: str = ""
    created: float
    frames_total: int | None = Field(None, description="frames the source will send (known once it starts)")
    frames_sent: int | None = Field(None, description="frames the source has sent (a camera session: relayed so far)")
    frames: int = Field(0, description="poses received")
    frames_dropped: int | None = Field(None, description="frames sent that got no pose (a camera-paced session "
                                       "drops frames its tracker cannot keep up with); a replay reports it once "
                                       "it has ended, a camera session as it goes")
    fps: float = 0.0
    latest_pose: PoseOut | None = None
    ate_rmse: float | None = Field(None, description="ATE RMSE in metres (SE(3), 0.02 s) of the served trajectory "
                                   "(`trajectory`), when ground truth exists")
    ate_rmse_online: float | None = Field(None, description="ATE RMSE of the poses as published (online)")
    trajectory: Literal["online", "refined"] = Field(
        "online", description="what GET .../trajectory serves: 'online' (the poses as published) until the tracker "
        "sends the refined trajectory after the session ends, then 'refined'")
    corrections: int = Field(0, description="live corrections received: keyframe poses after bundle adjustment")
    health: Literal["ok", "degraded", "relocalising"] = Field(
        "ok", description="the tracker's word on a live session: 'degraded' when it drops frames or its keyframe "
        "jobs come back late; 'relocalising' while it looks for the camera in the session's map (a map to localize "
        "in, or the snapshot a session moved with)")
    health_detail: str = Field("", description="why, with the figures: frames dropped, keyframe lag, CPU per frame")
    record: bool
    recording: str | None = None
    map: MapRequest | None = None
    start: int = 0
    tracker: str = Field("", description="the tracker replica serving the session, where the stack runs several "
                         "('' = the stack's one tracker)")
    moves: int = Field(0, description="times the session moved to another tracker because its own died (it goes on "
                       "in its map's latest snapshot, its poses in the same frame)")
    frame_id: str = Field("", description="the frame of its latest pose: the map's, '' for the robot's own, "
                          "<map>/<robot> in a shared map until the robot was merged")
    merge: MergeOut | None = Field(None, description="a session that shares a map: when and how its robot was placed "
                                   "in the map's frame")


class PoseRecord:
    """A session's poses as they arrived, kept compactly: one row of 9 floats per pose (frame index, stamp,
    position, quaternion), so that an hours-long session holds megabytes, not a message object per frame."""

    def __init__(self) -> None:
        self._rows = np.zeros((256, 9))
        self._count = 0
        self.latest: PoseMsg | None = None

    def __len__(self) -> int:
        return self._count

    def append(self, pose: PoseMsg, T: np.ndarray | None = None) -> None:
        """Keep a pose (``T``: moved by this transform first, a pose published before its robot was merged)."""
        if T is not None:
            in_map = T @ make_pose(quat_to_rot(np.array(pose.orientation)), np.array(pose.position))
            pose = pose.model_copy(update={"position": in_map[:3, 3].tolist(),
                                           "orientation": rot_to_quat(in_map[:3, :3]).tolist()})
        if self._count == len(self._rows):
            self._rows = np.concatenate([self._rows, np.zeros_like(self._rows)])
        self._rows[self._count] = [pose.frame_index, pose.stamp, *pose.position, *pose.orientation]
        self._count += 1
        self.latest = pose

    def move(self, T: np.ndarray) -> None:
        """Every pose kept so far moved by ``T`` (its robot was merged into a shared map's frame)."""
        rows = self._rows[:self._count]
        if not len(rows):
            return
        poses = T @ Trajectory.from_tum_array(rows[:, 1:9]).poses
        rows[:, 2:5] = poses[:, :3, 3]
        rows[:, 5:9] = [rot_to_quat(pose[:3, :3]) for pose in poses]

    def distinct_frames(self) -> int:
        """How many different frames got a pose."""
        return len(np.unique(self._rows[:self._count, 0]))

    def trajectory(self) -> Trajectory:
        """The poses as a camera-to-world trajectory, ordered by frame."""
        rows = self._rows[:self._count]
        rows = rows[np.argsort(rows[:, 0], kind="stable")]
        return Trajectory.from_tum_array(rows[:, 1:9])  # stamp, position, quaternion


@dataclass
class Session:
    id: str
    request: SessionRequest
    folder: Path | None  # the sequence of a replay; None for a camera session
    started_by: str = OPERATOR
    """who started it: the operator, or the robot whose token did (a map it saves is checked against them)"""
    state: SessionState = "starting"
    detail: str = ""
    created: float = field(default_factory=time.time)
    frames_total: int | None = None
    frames_sent: int | None = None
    poses: PoseRecord = field(default_factory=PoseRecord)
    first_pose_at: float | None = None
    last_pose_at: float | None = None
    started_at: float = field(default_factory=time.time)
    source_done_at: float | None = None
    ate_rmse: float | None = None
    ate_rmse_online: float | None = None
    finalising: bool = False
    refined: Trajectory | None = None
    """the refined trajectory the tracker sent when the session ended"""
    refined_due: float | None = None
    """until when the refined trajectory is worth waiting for (set when the session's stop is sent)"""
    corrections: int = 0
    health: Literal["ok", "degraded", "relocalising"] = "ok"
    health_detail: str = ""
    unposed: int = 0
    """frames the tracker answered with no pose (still looking for the camera in the session's map)"""
    unposed_at: float | None = None
    tracker: str = ""
    """the tracker replica serving it ('' = every tracker: a stack with one)"""
    config: PipelineConfig | None = None
    """the pipeline config it runs with (a tracker it moves to is given it again)"""
    moves: int = 0
    merge: MergeOut | None = None
    """where a session that shares a map was placed in the map's frame"""
    merge_T: np.ndarray | None = None

    def trajectory(self) -> Trajectory:
        """The poses as published (online), ordered by frame."""
        return self.poses.trajectory()

    def fps(self) -> float:
        if len(self.poses) < 2 or self.first_pose_at is None or self.last_pose_at == self.first_pose_at:
            return 0.0
        return (len(self.poses) - 1) / (self.last_pose_at - self.first_pose_at)


def _after_online(online: Trajectory, refined: Trajectory) -> Trajectory:
    """A moved session's whole trajectory: its refined one comes from the tracker it moved to, and covers only the
    frames that one tracked; the poses published before them go first, as they were."""
    before = online.stamps < (refined.stamps[0] if len(refined) else np.inf)
    return Trajectory(np.concatenate([online.stamps[before], refined.stamps]),
                      np.concatenate([online.poses[before], refined.poses]))


class SessionTable:
    """Thread-safe table of sessions, fed by bus callbacks and read by HTTP handlers."""

    def __init__(self) -> None:
        self.sessions: dict[str, Session] = {}
        self.lock = threading.Lock()

    def add(self, session: Session) -> None:
        with self.lock:
            self.sessions[session.id] = session

    def get(self, session_id: str) -> Session | None:
        with self.lock:
            return self.sessions.get(session_id)

    def active(self) -> list[Session]:
        """The sessions starting or running."""
        with self.lock:
            return [s for s in self.sessions.values() if s.state in ACTIVE]

    def active_for_robot(self, robot_id: str) -> Session | None:
        with self.lock:
            return next((s for s in self.sessions.values()
                         if s.request.robot_id == robot_id and s.state in ACTIVE), None)

    def on_pose(self, pose: PoseMsg) -> None:
        with self.lock:
            session = self.sessions.get(pose.session_id)
            if session is None or session.request.robot_id != pose.robot_id:
                return
            now = time.time()
            # a pose of the robot's own frame that crossed its merge on the way: moved as the earlier ones were
            late = session.merge_T is not None and pose.frame_id != session.merge.frame_id
            session.poses.append(pose, session.merge_T if late else None)
            session.first_pose_at = session.first_pose_at or now
            session.last_pose_at = now
            if session.state == "starting":
                session.state = "running"

    def on_merge(self, merge: MergeMsg) -> None:
        """A session's robot placed in a shared map's frame: its poses so far are moved there."""
        with self.lock:
            session = self.sessions.get(merge.session_id)
            if session is None or session.request.robot_id != merge.robot_id or session.request.map is None or (
                    session.request.map.name != merge.map_name):
                return
            T = merge.transform
            # the poses kept so far are in the robot's own frame, or (refined) in the map's by the earlier transform
            session.poses.move(T if session.merge_T is None else T @ invert_pose(session.merge_T))
            session.merge_T = T
            if merge.kind == "refined" and session.merge is not None:
                session.merge = session.merge.model_copy(update={
                    "inliers": merge.inliers, "position": merge.position, "orientation": merge.orientation,
                    "refinements": session.merge.refinements + 1})
                return
            session.merge = MergeOut(kind=merge.kind, frame_id=merge.map_name, at=merge.at, into=merge.into,
                                     inliers=merge.inliers, keyframes=merge.keyframes, ms=merge.ms,
                                     position=merge.position, orientation=merge.orientation)

    def on_path(self, path: PathMsg, trajectory: Trajectory) -> Session | None:
        """A corrected path from the tracker; returns the session when it is the final, refined trajectory."""
        with self.lock:
            session = self.sessions.get(path.session_id)
            if session is None or session.request.robot_id != path.robot_id:
                return None
            if not path.final:
                session.corrections += 1
                return None
            session.refined = trajectory if not session.moves else _after_online(session.trajectory(), trajectory)
            return session

    def on_status(self, status: StatusMsg) -> Session | None:
        """Follow a session's status; returns the session if this status failed it (a service reported an error)."""
        with self.lock:
            session = self.sessions.get(status.session_id)
            if session is None or session.request.robot_id != status.robot_id or session.state not in ACTIVE:
                return None
            if status.state == "error":
                session.state, session.detail = "failed", status.detail or f"the {status.service} service failed"
                return session
            if status.service == "tracker" and status.state == "relocalising":  # a frame answered with no pose
                session.health, session.health_detail = status.state, status.detail
                session.unposed += 1
                session.unposed_at = time.time()
                session.state = "running" if session.state == "starting" else session.state
                return None
            if status.service == "tracker" and status.state in ("ok", "degraded"):
                session.health, session.health_detail = status.state, status.detail
                return None
            if status.service != "source":
                return None
            if status.state == "relaying":
                session.frames_sent = status.counters.get("frames", 0)
            elif status.state == "started":
                session.state = "running" if session.state == "starting" else session.state
                session.frames_total = status.counters.get("frames")
            elif status.state in ("finished", "stopped"):
                session.frames_sent = status.counters.get("frames", 0)
                session.source_done_at = time.time()
        return None

    def fail_active(self, reason: str, which=lambda session: True) -> list[Session]:
        """Fail every active session (of those ``which`` picks: a service they need went away); returns them."""
        with self.lock:
            failed = [s for s in self.sessions.values() if s.state in ACTIVE and which(s)]
            for s in failed:
                s.state, s.detail = "failed", reason
        return failed

    def stalled_sessions(self, start_timeout: float, stall_timeout: float) -> list[Session]:
        """Active sessions that got no pose within ``start_timeout`` of their start, or none for ``stall_timeout``
        while their source was still sending; they are marked failed and returned."""
        now = time.time()
        stalled = []
        with self.lock:
            for s in self.sessions.values():
                if s.state not in ACTIVE or s.source_done_at is not None or s.request.source == "camera":
                    continue  # a camera may start late or pause; only a lost service fails a live session
                answered_at = max(s.last_pose_at or 0, s.unposed_at or 0) or None  # a pose, or a frame without
                if answered_at is None and now - s.started_at > start_timeout:
                    s.state, s.detail = "failed", f"no pose within {start_timeout:.0f} s of the start"
                elif answered_at is not None and now - answered_at > stall_timeout:
                    s.state, s.detail = "failed", f"no pose for {stall_timeout:.0f} s: the pipeline stalled"
                else:
                    continue
                stalled.append(s)
        return stalled

    def forget_ended(self, keep: int) -> None:
        """Keep at most ``keep`` ended sessions (the oldest go), so the table stays bounded."""
        with self.lock:
            ended = sorted((s for s in self.sessions.values() if s.state not in ACTIVE), key=lambda s: s.created)
            for s in ended[:max(0, len(ended) - keep)]:
                del self.sessions[s.id]

    def finished_sessions(self, idle_timeout: float) -> list[Session]:
        """Running sessions whose source is done and whose last pose arrived (or that went quiet)."""
        now = time.time()
        done = []
        with self.lock:
            for s in self.sessions.values():
                if s.state not in ACTIVE or s.source_done_at is None:
                    continue
                last = max(s.source_done_at, s.last_pose_at or 0, s.unposed_at or 0)
                answered = len(s.poses) + s.unposed
                if (answered >= (s.frames_sent or 0) or now - last > idle_timeout) and not s.finalising:
                    s.finalising = True
                    done.append(s)
        return done
