"""The tracker service: publishes each frame's pose on ``twohr/<robot>/pose``, in the session's schedule.

* ``keyframes`` (default): every frame from ``frames`` is tracked by optical flow in this process (the
  keyframe pipeline, :class:`~twohr_services.pipeline.KeyframePipeline`, as in ``twohr run``); its workers
  ask the detector (``rpc/detect``), yolo (``rpc/dynamics``) and matcher (``rpc/match``) services for
  keyframes and masks, so a pose never waits for a network.
* ``every_frame``: joins ``frames`` (depth), ``keypoints`` and ``dynamics`` of each frame, asks the matcher
  service for correspondences, and tracks with the keyframe tracker on every frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from twohr import keys
from twohr.dataset import Frame, depth_in_metres, undistorted
from twohr.features import Keypoints, Matches, drop_masked
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
    decode_array,
    decode_gray,
    encode,
    split,
)
from twohr.service import Service, serve

from .core import Tracker
from .keyframes import KeyframePipeline, Stages, map_snapshot


class RemoteStage:
    """A network stage in another service, asked over the bus with the frame message as the source sent it."""

    def __init__(self, session: zenoh.Session, robot_id: str, query: str, parse, timeout: float = 10.0) -> None:
        self.session, self.key, self.parse, self.timeout = session, keys.key(robot_id, query), parse, timeout

    def __call__(self, frame, source: bytes):
        for reply in self.session.get(self.key, payload=source, timeout=self.timeout):
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
    """A match function that asks the matcher service over Zenoh (query/reply)."""

    def __init__(self, session: zenoh.Session, robot_id: str, session_id: str, timeout: float = 10.0) -> None:
        self.session = session
        self.key = keys.key(robot_id, keys.MATCH_QUERY)
        self.robot_id, self.session_id = robot_id, session_id
        self.timeout = timeout
        self.frame_index, self.stamp = -1, 0.0

    def __call__(self, desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
        request = MatchRequestMsg(session_id=self.session_id, robot_id=self.robot_id, frame_index=self.frame_index,
                                  stamp=self.stamp, reference="local map")
        payload = encode(request, {"desc_a": desc_a, "desc_b": desc_b})
        for reply in self.session.get(self.key, payload=payload, timeout=self.timeout):
            if reply.ok is not None:
                _, arrays = decode(reply.ok.payload.to_bytes(), MatchesMsg)
                return Matches(arrays["idx_a"], arrays["idx_b"], arrays["scores"])
            raise MessageError(f"matcher service error: {reply.err.payload.to_bytes().decode(errors='replace')}")
        raise TimeoutError(f"no matcher service answered on {self.key} within {self.timeout} s")


@dataclass
class PendingFrame:
    stamp: float = 0.0
    depth: np.ndarray | None = None
    sent_at: float = 0.0
    keypoints: Keypoints | None = None
    mask: np.ndarray | None = None
    have_dynamics: bool = False
    elapsed: dict[str, float] = field(default_factory=dict)


@dataclass
class SessionTrack:
    tracker: Tracker | None
    matcher: RemoteMatcher
    needs_dynamics: bool
    pending: dict[int, PendingFrame] = field(default_factory=dict)
    last_index: int = -1
    pipeline: KeyframePipeline | None = None  # the keyframes schedule
    dropped: int = 0  # frames dropped because newer ones were waiting
    skipped: int = 0  # of them, in a row since the last tracked frame
    map_sent: int = -1  # the map version last published on ``landmarks``



class TrackerService(Service):
    """One tracker per session; a frame is tracked once its depth, keypoints and (if enabled) mask arrived."""

    name = "tracker"
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=64, policy="backpressure")
        self.tracks: dict[str, SessionTrack] = {}
        self.paced: dict[str, bool] = {}

    def subscriptions(self) -> list[str]:
        return [keys.all_robots(s) for s in ("frames", "keypoints", "dynamics")]

    def on_session_stop(self, session_id: str) -> None:
        self.paced.pop(session_id, None)
        track = self.tracks.pop(session_id, None)
        if track is not None and track.pipeline is not None:
            track.pipeline.close()

    def _track_for(self, session_id: str, robot_id: str, frame: FrameMsg | None) -> SessionTrack | None:
        if session_id not in self.tracks:
            if frame is None:
                return None  # the camera intrinsics come with the first frame
            config = self.config_for(session_id)
            matcher = RemoteMatcher(self.session, robot_id, session_id)
            if config.pipeline.mode == "keyframes":
                stages = Stages(RemoteStage(self.session, robot_id, keys.DETECT_QUERY, _keypoints_reply),
                                RemoteStage(self.session, robot_id, keys.DYNAMICS_QUERY, _dynamics_reply)
                                if config.yolo.enabled else None, matcher)
                pipeline = KeyframePipeline(config, frame.camera, stages, live=True)
                self.tracks[session_id] = SessionTrack(None, matcher, False, pipeline=pipeline)
            else:
                self.tracks[session_id] = SessionTrack(Tracker(frame.camera, config.tracker, match=matcher), matcher,
                                                       config.yolo.enabled)
        return self.tracks[session_id]

    def handle(self, key: str, payload: bytes) -> None:
        _, stream = keys.parse(key)
        if stream == "frames":
            frame, _ = decode(payload, FrameMsg, only=())
            track = self._track_for(frame.session_id, frame.robot_id, frame)
            if track.pipeline is not None:
                self._track_live(track, frame, payload)
                return
            _, arrays = decode(payload, FrameMsg, only=("depth",))
            entry = track.pending.setdefault(frame.frame_index, PendingFrame())
            entry.stamp, entry.sent_at = frame.stamp, frame.sent_at
            entry.depth = depth_in_metres(arrays["depth"], frame.camera)
            message = frame
        elif stream == "keypoints":
            message, arrays = decode(payload, KeypointsMsg)
            track = self._track_for(message.session_id, message.robot_id, None)
            if track is None or track.pipeline is not None:
                return
            entry = track.pending.setdefault(message.frame_index, PendingFrame())
            entry.keypoints = Keypoints(arrays["xy"], arrays["descriptors"], arrays["scores"],
                                        arrays.get("reliability"), arrays.get("repeatability"))
            entry.elapsed["detector"] = message.elapsed_ms
        elif stream == "dynamics":
            message, arrays = decode(payload, DynamicsMsg, only=("mask",))
            track = self._track_for(message.session_id, message.robot_id, None)
            if track is None or track.pipeline is not None:
                return
            entry = track.pending.setdefault(message.frame_index, PendingFrame())
            entry.mask, entry.have_dynamics = arrays["mask"].astype(bool), True
            entry.elapsed["yolo"] = message.elapsed_ms
        else:
            return
        self._track_ready(track, message)

    def _track_ready(self, track: SessionTrack, message) -> None:
        for index in sorted(track.pending):
            entry = track.pending[index]
            if index <= track.last_index:
                del track.pending[index]  # late part of a frame already passed over
                continue
            complete = entry.depth is not None and entry.keypoints is not None and (
                entry.have_dynamics or not track.needs_dynamics)
            if not complete:
                continue
            for older in [i for i in track.pending if i < index]:
                del track.pending[older]  # never completed (a stage dropped it): skip it
            del track.pending[index]
            track.last_index = index
            self._track_frame(track, message.session_id, message.robot_id, index, entry)

    def _track_live(self, track: SessionTrack, header: FrameMsg, payload: bytes) -> None:
        """The keyframes schedule: track this frame now; keyframe and mask work goes to the pipeline's workers.
        In a session paced by the camera, a frame that waited too long while newer ones queued is dropped:
        fresh data wins (a paced source does not wait for poses, so nothing stalls), but never more than
        ``max_skipped_frames`` in a row, so the optical flow keeps short steps while it catches up."""
        config = self.config_for(header.session_id)
        waited_ms = (time.time() - header.sent_at) * 1000 if header.sent_at else 0.0
        stale = len(self.inbox) and waited_ms > config.pipeline.max_frame_age_ms
        if self.paced.get(header.session_id) and stale and track.skipped < config.pipeline.max_skipped_frames:
            self.counters.add("dropped")
            track.dropped += 1
            track.skipped += 1
            return
        track.skipped = 0
        # the flow needs only grey levels (decoding a JPEG straight to grey is 3x faster); the keyframe stages
        # get the frame as it came, from the detector and yolo services
        _, parts = split(payload, FrameMsg)
        images = {spec.name: (spec, blob) for spec, blob in parts}
        gray = undistorted(decode_gray(*images["rgb"]), header.camera)
        depth = depth_in_metres(decode_array(*images["depth"]), header.camera)
        frame = Frame(header.frame_index, header.stamp, None, depth)
        track.matcher.frame_index, track.matcher.stamp = header.frame_index, header.stamp
        result, stats = track.pipeline.process(frame, source=payload, gray=gray)
        self._publish_pose(header.session_id, header.robot_id, header.frame_index, header.stamp, result,
                           stats.keypoints, header.sent_at, {"tracker": stats.ms_total})
        self._publish_map(track, header.session_id, header.robot_id, header.frame_index, header.stamp)

    def _track_frame(self, track: SessionTrack, session_id: str, robot_id: str, index: int,
                     entry: PendingFrame) -> None:
        kept = entry.keypoints if entry.mask is None else drop_masked(entry.keypoints, entry.mask)
        track.matcher.frame_index, track.matcher.stamp = index, entry.stamp
        t0 = time.perf_counter()
        result = track.tracker.track(entry.stamp, kept, entry.depth)
        elapsed = {**entry.elapsed, "tracker": (time.perf_counter() - t0) * 1000}
        self._publish_pose(session_id, robot_id, index, entry.stamp, result, len(kept), entry.sent_at, elapsed)
        self._publish_map(track, session_id, robot_id, index, entry.stamp)

    def _publish_map(self, track: SessionTrack, session_id: str, robot_id: str, index: int, stamp: float) -> None:
        """The map points on ``landmarks``, whenever a keyframe has changed the map."""
        version, points = map_snapshot(track.pipeline or track.tracker, since=track.map_sent)
        if points is None or not len(points):
            return
        track.map_sent = version
        message = LandmarksMsg(session_id=session_id, robot_id=robot_id, frame_index=index, stamp=stamp)
        self.publish(keys.key(robot_id, "landmarks"), encode(message, {"points": points.astype(np.float32)}))

    def _publish_pose(self, session_id: str, robot_id: str, index: int, stamp: float, result, num_keypoints: int,
                      sent_at: float, elapsed: dict[str, float]) -> None:
        pose = PoseMsg(session_id=session_id, robot_id=robot_id, frame_index=index, stamp=stamp,
                       position=result.pose[:3, 3].tolist(), orientation=rot_to_quat(result.pose[:3, :3]).tolist(),
                       status=result.status, num_keypoints=num_keypoints, num_matches=result.num_matches,
                       num_inliers=result.num_inliers, is_keyframe=result.is_keyframe, frame_sent_at=sent_at,
                       elapsed_ms=elapsed)
        self.publish(keys.key(robot_id, "pose"), encode(pose))

    def on_session_start(self, control: ControlMsg) -> None:
        self.on_session_stop(control.session_id)
        # paced by the camera (a real-rate replay or a live camera): the source never waits for poses
        self.paced[control.session_id] = control.rate > 0 or not control.sequence


def main(argv: list[str] | None = None) -> None:
    serve(TrackerService, argv)
