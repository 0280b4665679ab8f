"""The one interface of the tracker room: a :class:`Schedule` takes frames and gives poses, whichever schedule it
is. ``twohr run``, the live view and the tracker service hold a Schedule and never ask which one."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.mapfile import MapArrays
from twohr.trajectory import Trajectory

from .every_frame import EveryFrameSchedule
from .keyframe_schedule import KeyframePipeline
from .loops import LoopLog
from .map import Map, MapSnapshot
from .stages import FrameStats, KeyframeLog, Stages
from .trajectory import TrackResult


class Schedule(Protocol):
    """How the stages and the tracker are run over one camera's frames (``pipeline.mode``)."""

    map: Map
    """the camera's map (given, or built by the schedule); read it after :meth:`finish`, not while frames flow (the
    worker threads change it): while they do, read :meth:`map_snapshot` or :meth:`map_copy`"""
    keyframe_log: list[KeyframeLog]
    """what each keyframe job cost (empty where keyframes are not built apart from the frames)"""
    mask: np.ndarray | None
    """the dynamic mask the latest frame was tracked with"""
    loop_log: LoopLog
    """loops detected, accepted, rejected and closed (none where loop closing is off)"""
    shed_jobs: int
    """keyframe jobs dropped from the queue because a newer one made them redundant (none where keyframes are not
    built apart from the frames)"""

    def process(self, frame: Frame) -> tuple[TrackResult, FrameStats]:
        """The pose of one frame (online: final when returned), and what each stage did with it."""

    def finish(self) -> None:
        """After the last frame: let running work finish and take its result."""

    def refine(self) -> None:
        """After :meth:`finish`: bundle adjustment over the whole map, which refines :meth:`trajectory`."""

    def trajectory(self) -> Trajectory:
        """Every frame's pose, re-attached to the keyframes as bundle adjustment left them (in the keyframes
        schedule, the latest frames also measured again against the refined landmarks), and smoothed."""

    def map_snapshot(self, since: int = -1) -> MapSnapshot | None:
        """A copy of the map (landmarks, keyframe poses and stamps) as the per-frame path has it, or None while
        its version (the number of keyframes) is still ``since``."""

    def map_copy(self) -> MapArrays | None:
        """The whole map as a map file's arrays, copied where no thread was changing it, or None where no copy is
        ready yet: a copy of the map kept outside the process (the service's snapshot)."""

    def close(self) -> None:
        """Stop any worker threads."""


def build_schedule(config: PipelineConfig, camera: CameraIntrinsics, stages: Stages, live: bool = False,
                   world: Map | None = None) -> Schedule:
    """The schedule that ``config.pipeline.mode`` names, over ``stages``. ``live``: frames come at the camera's pace
    (a camera, a replay at its rate), so the per-frame path never waits for a keyframe job (a replay paced by the
    poses may, see ``max_keyframe_lag``). ``world``:
    a map to track in (loaded from a file), whose frame the poses are in once the camera is found in it."""
    if config.pipeline.mode == "keyframes":
        return KeyframePipeline(config, camera, stages, live=live, world=world)
    return EveryFrameSchedule(config, camera, stages, world=world)
