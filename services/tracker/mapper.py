"""The mapping worker: keyframe work off the per-frame path, over the map of one :class:`~.tracking.Tracker`.

:class:`Mapper` takes the worker's jobs (:class:`KeyframeJob`, :class:`Detected`, a verified
:class:`~twohr.places.PlaceMatch`: a loop) and returns each to the schedule as a :class:`~.flow.MapUpdate`. It sits
above the tracker and its :class:`~.mapping.LocalMapping`, as the thread that drives them.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import Frame
from twohr.features import Keypoints, drop_masked
from twohr.geometry import invert_pose
from twohr.places import PlaceMatch, PlaceQuery, Vocabulary, vocabulary_path
from twohr.pose import sample_depth

from .flow import MapUpdate, new_corners, on_flat_depth, static_in_reference
from .loops import LoopClosing, LoopLog
from .map import MapSnapshot
from .stages import Stages
from .tracking import Tracker
from .trajectory import TrackResult


@dataclass
class KeyframeJob:
    """A frame handed to the mapping worker, with the pose optical flow gave it. With ``tracks`` (the frame's
    inlier tracks: image positions and landmark ids) it becomes a tracked keyframe, without a network; without,
    the 2HR detector runs on it first (the first map, a lost camera, relocalisation)."""

    frame: Frame
    pose: np.ndarray
    tracks: tuple[np.ndarray, np.ndarray] | None = None
    mask: np.ndarray | None = None
    """the dynamic mask the per-frame path used for this frame (None: none fresh enough)"""
    reference: tuple[np.ndarray, int] | None = None
    """(grayscale image, keyframe id) of the latest keyframe: new corners must be static against it"""
    number: int = 0
    """the schedule's count of the frame (frame indices may start again)"""


@dataclass
class Detected:
    """2HR keypoints of an earlier tracked keyframe, detected off the mapping path, for the map to join."""

    keyframe_id: int
    frame: Frame
    keypoints: Keypoints
    """those outside the keyframe's dynamic mask"""
    ms_detector: float
    detected_count: int
    """the keypoints detected, the masked ones included"""


class Mapper:
    """The mapping worker: keyframe work, off the per-frame path, over the :class:`~.map.Map` of ``tracker`` (a
    :class:`~.tracking.Tracker` and its :class:`LocalMapping`): tracked keyframes (tracks and new corners, local
    bundle adjustment), 2HR keyframe jobs (YOLO and 2HR detection, then tracking against the local map, keyframe
    insertion, local bundle adjustment and relocalisation), the 2HR keypoints of earlier tracked keyframes joined to
    the map (:meth:`describe`), and verified loops closed (:meth:`close_loop`)."""

    def __init__(self, config: PipelineConfig, tracker: Tracker, stages: Stages) -> None:
        world = tracker.map
        self.stages = stages
        self.map = world
        self.conf = config.tracker
        self.tracker = tracker
        self.local_mapping = tracker.local_mapping
        self.asking = ThreadPoolExecutor(1, thread_name_prefix="twohr-mask")
        """asks for a keyframe's dynamic mask while the detector runs"""
        self.loops = None
        self.loop_log = LoopLog()
        self._released: list[np.ndarray] = []  # map rows the per-frame path gave back, for the next job to free
        self.copy_wanted = False  # the per-frame path asks for a copy of the whole map after the next job
        if config.loop_closing.vocabulary is not None:
            vocabulary = Vocabulary.load(vocabulary_path(config.loop_closing.vocabulary))
            self.loops = LoopClosing(world, vocabulary, config.loop_closing)

    def close(self) -> None:
        """Stop the thread that asks for masks."""
        self.asking.shutdown()

    @property
    def given_map(self) -> bool:
        """The map came with the session (loaded from a file): no pose before the camera is found in it."""
        return self.tracker.given_map

    def release(self, rows: np.ndarray) -> None:
        """The per-frame path holds none of these landmark rows (offered in a :class:`~.flow.MapUpdate`'s
        ``idle_rows``): the next job lets new landmarks fill them. Called from the per-frame path's thread."""
        self._released.append(rows)

    def __call__(self, job: KeyframeJob | Detected | PlaceMatch) -> MapUpdate:
        t0 = time.perf_counter()
        while self._released:
            self.map.reuse_rows(self._released.pop(0))
        if isinstance(job, Detected):
            update = self.describe(job)
        elif isinstance(job, PlaceMatch):
            update = self.close_loop(job)
        elif job.tracks is not None and self.tracker.localised:
            update = self._tracked_keyframe(job)
        else:
            update = self._detected_keyframe(job)
        if self.conf.reuse_landmark_rows and update.kind != "loop" and self.tracker.localised:
            update.idle_rows = self.map.idle_rows()
        if self.copy_wanted and self.map.keyframes:  # taken here: no other thread changes the map now
            self.copy_wanted = False
            update.arrays = self.map.arrays()
        update.timings["job"] = (time.perf_counter() - t0) * 1000
        return update

    def _keypoints_and_mask(self, job: KeyframeJob) -> tuple[Keypoints, np.ndarray | None, float, float]:
        """The frame's 2HR keypoints and its dynamic mask, asked at once (neither needs the other); the mask the job
        carries is the frame's own, so it is not asked again. Returns (keypoints, mask, ms detector, ms yolo: the wait
        for the mask after the keypoints came)."""
        frame, mask = job.frame, job.mask
        asked = None
        t0 = time.perf_counter()
        if mask is None and self.stages.dynamic_mask is not None:
            asked = self.asking.submit(self.stages.dynamic_mask, frame)
        keypoints = self.stages.detect(frame)
        t1 = time.perf_counter()
        if asked is not None:
            mask, _ = asked.result()
        return keypoints, mask, (t1 - t0) * 1000, (time.perf_counter() - t1) * 1000

    def _tracked_keyframe(self, job: KeyframeJob) -> MapUpdate:
        frame = job.frame
        t0 = time.perf_counter()
        mask = job.mask
        if mask is None and self.stages.dynamic_mask is not None:
            mask, _ = self.stages.dynamic_mask(frame)
        t1 = time.perf_counter()
        tracks_xy, tracks_landmark = job.tracks
        corners = new_corners(frame.gray, self.conf.keyframe_corners, self.conf.corner_min_distance_px, mask,
                              tracks_xy)
        corners = corners[on_flat_depth(frame.depth, corners, self.conf.corner_depth_radius_px,
                                        self.conf.depth_edge_ratio)]
        if job.reference is not None and len(corners):
            reference, keyframe_id = job.reference
            z = sample_depth(frame.depth, corners, self.conf.min_depth, self.conf.max_depth,
                             self.conf.depth_edge_ratio)
            corners, z = corners[z > 0], z[z > 0]
            corners = corners[static_in_reference(frame.gray, job.pose, corners, z, reference,
                                                  self.map.keyframe_poses[keyframe_id], self.map.K, self.conf)]
        result = self.local_mapping.add_tracked_keyframe(frame.stamp, job.pose, tracks_xy, tracks_landmark, corners,
                                                   frame.depth)
        keyframe_id = self.map.keyframes[-1].id if result.is_keyframe else -1
        timings = {"detector": 0.0, "yolo": (t1 - t0) * 1000, "mapping": (time.perf_counter() - t1) * 1000}
        return MapUpdate(frame.index, frame.stamp, result, keyframe_id, result.observed_xy, result.observed_landmarks,
                         self.map.snapshot(), frame.gray, timings, keypoints=len(corners), kept=len(corners),
                         kind="tracked", mask=mask)

    def _detected_keyframe(self, job: KeyframeJob) -> MapUpdate:
        frame = job.frame
        keypoints, mask, ms_detector, ms_yolo = self._keypoints_and_mask(job)
        kept = keypoints if mask is None else drop_masked(keypoints, mask)
        t2 = time.perf_counter()
        tracker = self.tracker
        prediction = job.pose if tracker.initialised else None
        result = tracker.track(frame.stamp, kept, frame.depth, prediction=prediction, force_keyframe=True,
                               match=self.stages.matcher_for(frame))
        seeds_xy, seeds_landmark = np.zeros((0, 2)), np.zeros(0, np.int64)
        if result.observed_landmarks is not None:
            # best observed first
            order = np.argsort(-self.map.landmarks.accepted[result.observed_landmarks], kind="stable")
            seeds_xy, seeds_landmark = result.observed_xy[order], result.observed_landmarks[order]
        keyframe_id = self.map.keyframes[-1].id if result.is_keyframe else -1
        t3 = time.perf_counter()
        timings = {"detector": ms_detector, "yolo": ms_yolo, "mapping": (t3 - t2) * 1000}
        # until the camera is found in a given map, the per-frame path gets none of it
        snapshot = self.map.snapshot() if tracker.localised else MapSnapshot.empty()
        return MapUpdate(frame.index, frame.stamp, result, keyframe_id, seeds_xy, seeds_landmark, snapshot,
                         frame.gray, timings, keypoints=len(keypoints), kept=len(kept),
                         loop_query=self._loop_query(keyframe_id))

    def _loop_query(self, keyframe_id: int) -> PlaceQuery | None:
        """Place recognition for a keyframe whose landmarks have descriptors (off without a vocabulary)."""
        if self.loops is None or keyframe_id < 0 or not self.tracker.localised:
            return None
        return self.loops.query(keyframe_id)

    def close_loop(self, loop: PlaceMatch) -> MapUpdate:
        """Correct the map for a verified loop (:meth:`~.loops.LoopClosing.close`); the per-frame path gets the
        corrected map, and its tracks follow the fused landmarks."""
        t0 = time.perf_counter()
        latest = self.map.keyframe_poses[-1].copy()
        closed = self.loops.close(loop, self.loops.conf.ba_iterations)
        self.tracker.motion.move_world(self.map.keyframe_poses[-1] @ invert_pose(latest))  # where the camera is
        self.loop_log.closed += 1
        self.loop_log.loops.append({**closed, "ms": round((time.perf_counter() - t0) * 1000, 1)})
        pose = self.map.keyframe_poses[loop.keyframe_id].copy()
        result = TrackResult(loop.stamp, pose, "loop", reason=f"loop closed at keyframe {loop.keyframe_id} against "
                             f"keyframe {loop.candidate_id}: {closed['correction_m']} m corrected")
        timings = {"detector": 0.0, "yolo": 0.0, "mapping": (time.perf_counter() - t0) * 1000}
        return MapUpdate(-1, loop.stamp, result, -1, np.zeros((0, 2)), np.zeros(0, np.int64), self.map.snapshot(),
                         None, timings, kind="loop", fused=loop.pairs)

    def detect(self, keyframe_id: int, frame: Frame, mask: np.ndarray | None) -> Detected:
        """The 2HR keypoints of tracked keyframe ``keyframe_id`` (outside its dynamic mask); reads no map, so it
        runs on its own worker while the mapping worker goes on."""
        t0 = time.perf_counter()
        keypoints = self.stages.detect(frame)
        kept = keypoints if mask is None else drop_masked(keypoints, mask)
        return Detected(keyframe_id, frame, kept, (time.perf_counter() - t0) * 1000, len(keypoints))

    def describe(self, detected: Detected) -> MapUpdate:
        """Join a tracked keyframe's 2HR keypoints to the map (:meth:`LocalMapping.describe_keyframe`); the
        landmarks they add come back as seeds for the per-frame path."""
        frame = detected.frame
        t0 = time.perf_counter()
        xy, landmark = self.local_mapping.describe_keyframe(detected.keyframe_id, detected.keypoints, frame.depth,
                                                      match=self.stages.matcher_for(frame))
        result = TrackResult(frame.stamp, self.map.keyframe_poses[detected.keyframe_id], "described",
                             num_keypoints=detected.detected_count, num_matches=len(detected.keypoints),
                             reason=f"2HR keypoints of keyframe {detected.keyframe_id} joined to the map")
        timings = {"detector": detected.ms_detector, "yolo": 0.0, "mapping": (time.perf_counter() - t0) * 1000}
        return MapUpdate(frame.index, frame.stamp, result, -1, xy, landmark, self.map.snapshot(), frame.gray,
                         timings, keypoints=detected.detected_count, kept=len(detected.keypoints), kind="describe",
                         loop_query=self._loop_query(detected.keyframe_id))
