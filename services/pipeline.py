"""The in-process pipeline on one machine, in one process: the composition root of ``twohr run`` and
``twohr bench``. The Zenoh services compose the very same cores across processes.

Two schedules (``pipeline.mode``):

* ``keyframes`` (default): :class:`~.tracker.keyframes.KeyframePipeline` with the networks of this process
  (:func:`local_stages`); the tracker service runs the same class with the networks behind the bus.
* ``every_frame`` (:class:`Pipeline`): detector -> yolo mask -> matcher -> tracker on every frame, as in
  the paper; kept for its ablations.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.features import Keypoints, drop_masked
from twohr.trajectory import Trajectory
from twohr.workers import prefetch

from .detector.core import build_detector
from .matcher.core import build_matcher
from .tracker.core import TRACKED_STATUSES, Tracker, TrackResult
from .tracker.keyframes import FrameStats, KeyframeLog, KeyframePipeline, Stages, online_trajectory
from .yolo.masks import DynamicMasker, propagated_mask


@dataclass
class StageOutput:
    """What the front end produced for a frame; cacheable so that tracker variants can reuse it."""

    keypoints: Keypoints
    mask: np.ndarray | None
    dynamic_objects: int
    ms_detector: float
    ms_yolo: float
    extra: dict = field(default_factory=dict)


class FrontEnd:
    """Keypoints and the dynamic mask of a frame (detector + yolo cores)."""

    def __init__(self, config: PipelineConfig) -> None:
        self.config = config
        self.detector = build_detector(config.detector)
        self.masker = DynamicMasker(config.yolo) if config.yolo.enabled else None

    def __call__(self, frame: Frame) -> StageOutput:
        t0 = time.perf_counter()
        keypoints = self.detector.detect(frame.rgb)
        t1 = time.perf_counter()
        mask, objects = None, 0
        if self.masker is not None:
            regions = self.masker(frame.rgb, frame.depth)
            mask, objects = regions.mask, len(regions.dynamic)
        t2 = time.perf_counter()
        return StageOutput(keypoints, mask, objects, (t1 - t0) * 1000, (t2 - t1) * 1000)


class Pipeline:
    """The whole SLAM pipeline for one camera. ``process(frame)`` returns the tracker's result and stats."""

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics) -> None:
        self.config = config
        self.front_end = FrontEnd(config)
        self.tracker = Tracker(camera, config.tracker, match=build_matcher(config.matcher))

    def process(self, frame: Frame, front: StageOutput | None = None) -> tuple[TrackResult, FrameStats]:
        """Track one frame; ``front`` reuses a cached front-end output instead of running the networks."""
        t0 = time.perf_counter()
        front = front or self.front_end(frame)
        kept = front.keypoints if front.mask is None else drop_masked(front.keypoints, front.mask)
        t1 = time.perf_counter()
        result = self.tracker.track(frame.stamp, kept, frame.depth)
        ms_tracker = (time.perf_counter() - t1) * 1000
        stats = FrameStats(
            index=frame.index, stamp=frame.stamp, status=result.status, keypoints=len(front.keypoints),
            kept=len(kept), with_depth=result.num_with_depth, matches=result.num_matches,
            inliers=result.num_inliers, keyframe=result.is_keyframe, dynamic_objects=front.dynamic_objects,
            mask_percent=0.0 if front.mask is None else float(100 * front.mask.mean()),
            ms_detector=front.ms_detector, ms_yolo=front.ms_yolo, ms_tracker=ms_tracker,
            ms_total=front.ms_detector + front.ms_yolo + (time.perf_counter() - t0) * 1000, reason=result.reason,
        )
        return result, stats

    def refine(self) -> None:
        """After the last frame: bundle adjustment over the whole map refines :attr:`tracker`'s trajectory."""
        self.tracker.final_bundle_adjustment()


def local_stages(config: PipelineConfig, camera: CameraIntrinsics) -> Stages:
    """The detector, YOLO and matcher cores in this process, compiled for the camera's image size."""
    detector = build_detector(config.detector)
    masker = DynamicMasker(config.yolo) if config.yolo.enabled else None
    blank = np.zeros((camera.height, camera.width, 3), np.uint8)
    detector.detect(blank)  # compile the networks for this size now, not on the first frames
    if masker is not None:
        masker.detect_dynamic(blank)

    def dynamic_mask(frame: Frame, _source) -> tuple[np.ndarray, int]:
        dynamic = masker.detect_dynamic(frame.rgb)
        return propagated_mask(dynamic, 0, frame.depth.shape, config.yolo, frame.depth), len(dynamic)

    return Stages(lambda frame, _: detector.detect(frame.rgb), None if masker is None else dynamic_mask,
                  build_matcher(config.matcher))


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

    @property
    def tracked_percent(self) -> float:
        ok = sum(s.status in TRACKED_STATUSES for s in self.stats)
        return 100.0 * ok / max(1, len(self.stats))



def run_sequence(sequence, config: PipelineConfig, start: int = 0, stop: int | None = None, step: int = 1,
                 progress: bool = True, front_cache: dict[int, StageOutput] | None = None,
                 on_frame: Callable[[Frame, TrackResult, FrameStats, object], None] | None = None) -> RunResult:
    """Run the pipeline over a sequence (``twohr.dataset.RGBDSequence``). Corrupt frames are skipped
    and counted. ``front_cache`` (frame index -> StageOutput) reuses or collects front-end outputs
    (``every_frame`` mode only). ``on_frame(frame, result, stats, pipeline)`` is called after each frame
    (e.g. a live view)."""
    from tqdm import tqdm

    keyframes = config.pipeline.mode == "keyframes"
    if keyframes:
        pipeline = KeyframePipeline(config, sequence.camera, local_stages(config, sequence.camera))
    else:
        pipeline = Pipeline(config, sequence.camera)
    results, stats = [], []
    stop = len(sequence) if stop is None else min(stop, len(sequence))
    t0 = time.perf_counter()
    bar = tqdm(total=len(range(start, stop, step)), disable=not progress, unit="frame", desc=sequence.name,
               dynamic_ncols=True)
    frames = sequence.frames(start, stop, step)
    if keyframes:
        frames = prefetch(frames, config.pipeline.prefetch)
    for frame in frames:
        if keyframes:
            result, row = pipeline.process(frame)
        else:
            front = None if front_cache is None else front_cache.get(frame.index)
            if front is None:
                front = pipeline.front_end(frame)
                if front_cache is not None:
                    front_cache[frame.index] = front
            result, row = pipeline.process(frame, front)
        results.append(result)
        stats.append(row)
        if on_frame is not None:
            on_frame(frame, result, row, pipeline)
        bar.set_postfix(status=row.status, kept=row.kept, inliers=row.inliers, refresh=False)
        bar.update(1)
    bar.update(bar.total - bar.n)
    bar.close()
    if keyframes:
        pipeline.finish()
    wall = time.perf_counter() - t0
    pipeline.refine()  # after the frames: a live camera would be done too
    refine_s = time.perf_counter() - t0 - wall
    online = online_trajectory(results)
    if not results:
        refined = online
    else:
        refined = pipeline.trajectory() if keyframes else pipeline.tracker.trajectory()
    keyframe_log = pipeline.keyframe_log if keyframes else []
    return RunResult(refined, online, stats, list(sequence.skipped), wall, keyframe_log, refine_s)
