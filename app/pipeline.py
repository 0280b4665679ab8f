"""The in-process pipeline on one machine, in one process: the composition root of ``twohr run`` and
``twohr bench``. The Zenoh services compose the very same cores across processes.

It builds the stages of this process (:func:`local_stages`: the detector, YOLO and matcher cores) and hands them
to the schedule that ``pipeline.mode`` names (:func:`~.tracker.schedule.build_schedule`): the camera-rate
``keyframes`` schedule (default) or ``every_frame``, as in the paper. The tracker service builds the same
schedules over the networks behind the bus.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.features import Keypoints
from twohr.keys import NETWORK_SERVICES
from twohr.trajectory import Trajectory
from twohr.workers import prefetch
from twohr_services.detector.core import R2D2Detector, build_detector
from twohr_services.matcher.core import build_matcher
from twohr_services.tracker.loops import LoopLog
from twohr_services.tracker.map import Map
from twohr_services.tracker.schedule import Schedule, build_schedule
from twohr_services.tracker.stages import FrameStats, KeyframeLog, Stages
from twohr_services.tracker.trajectory import TRACKED_STATUSES, TrackResult
from twohr_services.yolo.masks import DynamicMasker


@dataclass
class StageOutput:
    """What the front end produced for a frame; cacheable so that tracker variants can reuse it."""

    keypoints: Keypoints
    mask: np.ndarray | None
    dynamic_objects: int
    ms_detector: float
    ms_yolo: float


class FrontEnd:
    """Keypoints and the dynamic mask of a frame (detector + yolo cores, in this process)."""

    def __init__(self, config: PipelineConfig, detector: bool = True) -> None:
        """``detector`` False: the dynamic masks alone (the keypoints come from elsewhere)."""
        self.config = config
        self.detector = build_detector(config.detector) if detector else None
        self.masker = DynamicMasker(config.yolo) if config.yolo.enabled else None

    def __call__(self, frame: Frame) -> StageOutput:
        t0 = time.perf_counter()
        keypoints = self.detector.detect(frame.rgb)
        t1 = time.perf_counter()
        mask, objects = self.dynamic_mask(frame) if self.masker is not None else (None, 0)
        t2 = time.perf_counter()
        return StageOutput(keypoints, mask, objects, (t1 - t0) * 1000, (t2 - t1) * 1000)

    def dynamic_mask(self, frame: Frame) -> tuple[np.ndarray, int]:
        """The frame's dynamic mask (True = moving) and how many dynamic objects it holds (``yolo.every_n``: the
        masker detects on every n-th call and propagates its boxes between)."""
        regions = self.masker(frame.rgb, frame.depth)
        return regions.mask, len(regions.dynamic)


def detector_provenance(detector, image_size: tuple[int, int]) -> dict:
    """What the detector chose on this machine: its network (``detector.model=auto``: with each candidate's timed
    latency) and input scale (``latency_budget_ms``)."""
    if not isinstance(detector, R2D2Detector):
        return {}
    chosen: dict = {"detector_model": detector.model}
    if detector.model_timings_ms:
        chosen["detector_model_timings_ms"] = {name: round(ms, 1) for name, ms in detector.model_timings_ms.items()}
        chosen["detector_model_timed_at"] = detector.model_timed_at
    if image_size in detector.input_scales:
        chosen["detector_input_scale"] = detector.input_scales[image_size]
    return chosen


def local_stages(config: PipelineConfig, camera: CameraIntrinsics,
                 here: tuple[str, ...] = NETWORK_SERVICES) -> Stages:
    """The detector, YOLO and matcher cores in this process, compiled for the camera's image size; with ``here``
    naming fewer of them, the others' stages raise until the caller puts its own in their place (a robot's own
    tracker asks the stack for some: :mod:`twohr_app.edge`)."""
    if set(here) - set(NETWORK_SERVICES):
        raise ValueError(f"stages here {here}: name some of {NETWORK_SERVICES}")
    front = FrontEnd(config, detector="detector" in here)
    blank = np.zeros((camera.height, camera.width, 3), np.uint8)
    if front.detector is not None:
        front.detector.detect(blank)  # compile the networks for this size now, not on the first frames
    masks = front.masker is not None and "yolo" in here
    if masks:
        front.masker.detect_dynamic(blank)
    matcher = build_matcher(config.matcher) if "matcher" in here else None
    return Stages(
        (lambda frame: front.detector.detect(frame.rgb)) if front.detector is not None else _runs_elsewhere,
        (front.dynamic_mask if masks else None) if "yolo" in here else _runs_elsewhere,
        (lambda _frame, desc_a, desc_b: matcher(desc_a, desc_b)) if matcher is not None else _runs_elsewhere,
        detector_provenance(front.detector, (camera.width, camera.height)) if front.detector is not None else {})


def _runs_elsewhere(*_args):
    raise RuntimeError("this stage runs elsewhere and was not given")


def cached_stages(config: PipelineConfig, cache: dict[int, StageOutput]) -> Stages:
    """Stages that answer from ``cache`` (frame index -> :class:`StageOutput`, for studies that run many tracker
    variants on one front end), running the networks and filling the cache only for frames it lacks."""
    fronts: list[FrontEnd] = []

    def output(frame: Frame) -> StageOutput:
        if frame.index not in cache:
            if not fronts:
                fronts.append(FrontEnd(config))
            cache[frame.index] = fronts[0](frame)
        return cache[frame.index]

    matcher = build_matcher(config.matcher)
    return Stages(lambda frame: output(frame).keypoints,
                  (lambda frame: (output(frame).mask, output(frame).dynamic_objects)) if config.yolo.enabled else None,
                  lambda _frame, desc_a, desc_b: matcher(desc_a, desc_b))


def stats_rows(stats: list[FrameStats]) -> list[dict]:
    return [asdict(s) for s in stats]


@dataclass
class RunResult:
    """Everything ``twohr run`` produces for one sequence."""

    trajectory: Trajectory
    online: Trajectory
    stats: list[FrameStats]
    skipped: list[int]
    wall_s: float
    keyframe_log: list[KeyframeLog] = field(default_factory=list)
    refine_s: float = 0.0
    """seconds of the final bundle adjustment, after the frames (not in ``wall_s``)"""
    map: Map | None = None
    """the schedule's map after the run (the one given, grown, or a new one)"""
    loops: LoopLog | None = None
    """loop closing's counts and closed loops (None: loop closing was off)"""
    chosen: dict[str, float] = field(default_factory=dict)
    """settings chosen at warm-up (:attr:`~.tracker.stages.Stages.chosen`)"""
    shed_jobs: int = 0
    """keyframe jobs the schedule's queue dropped as stale"""

    @property
    def tracked_percent(self) -> float:
        ok = sum(s.status in TRACKED_STATUSES for s in self.stats)
        return 100.0 * ok / max(1, len(self.stats))


def run_sequence(sequence, config: PipelineConfig, start: int = 0, stop: int | None = None, step: int = 1,
                 progress: bool = True, front_cache: dict[int, StageOutput] | None = None,
                 on_frame: Callable[[Frame, TrackResult, FrameStats, Schedule], None] | None = None,
                 world: Map | None = None) -> RunResult:
    """Run the pipeline over a sequence (``twohr.dataset.RGBDSequence``). Corrupt frames are skipped
    and counted. ``front_cache`` (frame index -> StageOutput) reuses or collects front-end outputs
    (see :func:`cached_stages`). ``on_frame(frame, result, stats, schedule)`` is called after each frame
    (e.g. a live view). ``world``: a map to track in (loaded from a file); the poses are in its frame, and frames
    before the camera is found in it have none."""
    from tqdm import tqdm

    if front_cache is None:
        stages = local_stages(config, sequence.camera)
    else:
        stages = cached_stages(config, front_cache)
    schedule = build_schedule(config, sequence.camera, stages, world=world)
    posed, stats = [], []  # (stamp, pose) of each posed frame: a long replay keeps no frame's arrays
    stop = len(sequence) if stop is None else min(stop, len(sequence))
    t0 = time.perf_counter()
    bar = tqdm(total=len(range(start, stop, step)), disable=not progress, unit="frame", desc=sequence.name,
               dynamic_ncols=True)
    for frame in prefetch(sequence.frames(start, stop, step), config.pipeline.prefetch):
        result, row = schedule.process(frame)
        if result.posed:
            posed.append((result.stamp, result.pose))
        stats.append(row)
        if on_frame is not None:
            on_frame(frame, result, row, schedule)
        bar.set_postfix(status=row.status, kept=row.kept, inliers=row.inliers, refresh=False)
        bar.update(1)
    bar.update(bar.total - bar.n)
    bar.close()
    schedule.finish()
    wall = time.perf_counter() - t0
    schedule.refine()  # after the frames: a live camera would be done too
    refine_s = time.perf_counter() - t0 - wall
    online = Trajectory(np.array([stamp for stamp, _ in posed]),
                        np.array([pose for _, pose in posed]).reshape(-1, 4, 4))
    refined = schedule.trajectory() if stats else online
    return RunResult(refined, online, stats, list(sequence.skipped), wall, schedule.keyframe_log, refine_s,
                     schedule.map, schedule.loop_log if config.loop_closing.vocabulary else None, stages.chosen,
                     schedule.shed_jobs)
