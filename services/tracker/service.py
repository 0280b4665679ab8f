"""The tracker service: publishes each frame's pose on ``twohr/<robot>/pose``, in the session's schedule.

It feeds every frame of ``frames`` to the session's :class:`~.schedule.Schedule` (built by
:func:`~.schedule.build_schedule`, as ``twohr run`` builds it) over stages that ask the detector
(``rpc/detect``), yolo (``rpc/dynamics``) and matcher (``rpc/match``) services. In the default ``keyframes``
schedule those are asked only for keyframes and every few frames' masks, from worker threads, so a pose never
waits for a network; in ``every_frame`` they are asked for every frame, in turn.

A session's trajectory over the bus is the poses as published (online); it is not refined after the session.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import zenoh

from twohr import keys
from twohr.dataset import Frame
from twohr.features import Keypoints, Matches
from twohr.geometry import rot_to_quat
from twohr.messages import (
    ControlMsg,
    DynamicsMsg,
    FrameMsg,
    KeypointsMsg,
    LandmarksMsg,
    MatchesMsg,
    MatchRequestMsg,
    MessageError,
    PoseMsg,
    decode,
    encode,
    received_frame,
)
from twohr.service import Service, serve

from .schedule import Schedule, build_schedule
from .stages import FrameStats, Stages
from .trajectory import TrackResult


class RemoteStage:
    """A network stage in another service, asked over the bus with the frame message as the source sent it."""

    def __init__(self, session: zenoh.Session, robot_id: str, query: str, parse, timeout: float = 10.0) -> None:
        self.session, self.key, self.parse, self.timeout = session, keys.key(robot_id, query), parse, timeout

    def __call__(self, frame: Frame):
        for reply in self.session.get(self.key, payload=frame.message, timeout=self.timeout):
            if reply.ok is not None:
                return self.parse(reply.ok.payload.to_bytes())
            raise MessageError(f"{self.key}: {reply.err.payload.to_bytes().decode(errors='replace')}")
        raise TimeoutError(f"no service answered on {self.key} within {self.timeout} s")


def _keypoints_reply(payload: bytes) -> Keypoints:
    _, arrays = decode(payload, KeypointsMsg)
    return Keypoints(arrays["xy"], arrays["descriptors"], arrays["scores"], arrays.get("reliability"),
                     arrays.get("repeatability"))


def _dynamics_reply(payload: bytes) -> tuple[np.ndarray, int]:
    message, arrays = decode(payload, DynamicsMsg, only=("mask",))
    return arrays["mask"].astype(bool), len(message.names)


class RemoteMatcher:
    """The match stage in the matcher service, asked over Zenoh (query/reply) for the frame it names."""

    def __init__(self, session: zenoh.Session, robot_id: str, session_id: str, timeout: float = 10.0) -> None:
        self.session = session
        self.key = keys.key(robot_id, keys.MATCH_QUERY)
        self.robot_id, self.session_id = robot_id, session_id
        self.timeout = timeout

    def __call__(self, frame: Frame, desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
        request = MatchRequestMsg(session_id=self.session_id, robot_id=self.robot_id, frame_index=frame.index,
                                  stamp=frame.stamp, reference="local map")
        payload = encode(request, {"desc_a": desc_a, "desc_b": desc_b})
        for reply in self.session.get(self.key, payload=payload, timeout=self.timeout):
            if reply.ok is not None:
                _, arrays = decode(reply.ok.payload.to_bytes(), MatchesMsg)
                return Matches(arrays["idx_a"], arrays["idx_b"], arrays["scores"])
            raise MessageError(f"matcher service error: {reply.err.payload.to_bytes().decode(errors='replace')}")
        raise TimeoutError(f"no matcher service answered on {self.key} within {self.timeout} s")


@dataclass
class SessionTrack:
    """One session's schedule and what the adapter counts for it."""

    schedule: Schedule
    dropped: int = 0  # frames dropped because newer ones were waiting
    skipped: int = 0  # of them, in a row since the last tracked frame
    map_sent: int = -1  # the map version last published on ``landmarks``


class TrackerService(Service):
    """One schedule per session, fed every frame of the session's robot; the networks are asked over the bus."""

    name = "tracker"
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=64, policy="backpressure")
        self.tracks: dict[str, SessionTrack] = {}
        self.paced: dict[str, bool] = {}

    def subscriptions(self) -> list[str]:
        return [keys.all_robots("frames")]

    def on_session_stop(self, session_id: str) -> None:
        self.paced.pop(session_id, None)
        track = self.tracks.pop(session_id, None)
        if track is not None:
            track.schedule.close()

    def _track_for(self, header: FrameMsg) -> SessionTrack:
        """The session's schedule, built on its first frame (the camera intrinsics come with the frames)."""
        if header.session_id not in self.tracks:
            config = self.config_for(header.session_id)
            robot_id = header.robot_id
            stages = Stages(RemoteStage(self.session, robot_id, keys.DETECT_QUERY, _keypoints_reply),
                            RemoteStage(self.session, robot_id, keys.DYNAMICS_QUERY, _dynamics_reply)
                            if config.yolo.enabled else None,
                            RemoteMatcher(self.session, robot_id, header.session_id))
            self.tracks[header.session_id] = SessionTrack(build_schedule(config, header.camera, stages, live=True))
        return self.tracks[header.session_id]

    def handle(self, key: str, payload: bytes) -> None:
        """Track one frame now; keyframe and mask work goes to the schedule's workers. In a session paced by the
        camera, a frame that waited too long while newer ones queued is dropped on its header, before any image
        is decoded: fresh data wins (a paced source does not wait for poses, so nothing stalls), but never more
        than ``max_skipped_frames`` in a row, so the optical flow keeps short steps while it catches up."""
        header, _ = decode(payload, FrameMsg, only=())
        config = self.config_for(header.session_id)
        track = self._track_for(header)
        waited_ms = (time.time() - header.sent_at) * 1000 if header.sent_at else 0.0
        stale = len(self.inbox) and waited_ms > config.pipeline.max_frame_age_ms
        if self.paced.get(header.session_id) and stale and track.skipped < config.pipeline.max_skipped_frames:
            self.counters.add("dropped")
            track.dropped += 1
            track.skipped += 1
            return
        track.skipped = 0
        _, frame = received_frame(payload)
        result, stats = track.schedule.process(frame)
        self._publish_pose(header, result, stats)
        self._publish_map(track, header)

    def _publish_map(self, track: SessionTrack, header: FrameMsg) -> None:
        """The map points on ``landmarks``, whenever a keyframe has changed the map."""
        version, points = track.schedule.map_snapshot(since=track.map_sent)
        if points is None or not len(points):
            return
        track.map_sent = version
        message = LandmarksMsg(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                               stamp=header.stamp)
        self.publish(keys.key(header.robot_id, "landmarks"), encode(message, {"points": points.astype(np.float32)}))

    def _publish_pose(self, header: FrameMsg, result: TrackResult, stats: FrameStats) -> None:
        pose = PoseMsg(session_id=header.session_id, robot_id=header.robot_id, frame_index=header.frame_index,
                       stamp=header.stamp, position=result.pose[:3, 3].tolist(),
                       orientation=rot_to_quat(result.pose[:3, :3]).tolist(), status=result.status,
                       num_keypoints=stats.keypoints, num_matches=result.num_matches, num_inliers=result.num_inliers,
                       is_keyframe=result.is_keyframe, frame_sent_at=header.sent_at,
                       elapsed_ms={"detector": stats.ms_detector, "yolo": stats.ms_yolo, "tracker": stats.ms_tracker})
        self.publish(keys.key(header.robot_id, "pose"), encode(pose))

    def on_session_start(self, control: ControlMsg) -> None:
        self.on_session_stop(control.session_id)
        # paced by the camera (a real-rate replay or a live camera): the source never waits for poses
        self.paced[control.session_id] = control.rate > 0 or not control.sequence


def main(argv: list[str] | None = None) -> None:
    serve(TrackerService, argv)
