"""The in-process pipeline: detector -> yolo mask -> matcher -> tracker, on one machine, in one process.

This is the composition root that ``twohr run`` and ``twohr bench`` use; the Zenoh services
compose the very same cores across processes.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.features import Keypoints, drop_masked
from twohr.trajectory import Trajectory

from .detector.core import build_detector
from .matcher.core import build_matcher
from .tracker.core import TRACKED_STATUSES, Tracker, TrackResult
from .yolo.masks import DynamicMasker


@dataclass
class FrameStats:
    """One row of ``stats.csv``: what each stage did with a frame, and how long it took (ms)."""

    index: int
    stamp: float
    status: str
    keypoints: int
    kept: int
    with_depth: int
    matches: int
    inliers: int
    keyframe: bool
    dynamic_objects: int
    mask_percent: float
    ms_detector: float
    ms_yolo: float
    ms_tracker: float
    ms_total: float
    reason: str = ""


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

    def online_trajectory(self, results: Iterable[TrackResult]) -> Trajectory:
        """The poses as they were estimated, frame by frame (what the tracker publishes live)."""
        results = list(results)
        return Trajectory(np.array([r.stamp for r in results]), np.array([r.pose for r in results]).reshape(-1, 4, 4))


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

    @property
    def tracked_percent(self) -> float:
        ok = sum(s.status in TRACKED_STATUSES for s in self.stats)
        return 100.0 * ok / max(1, len(self.stats))



def run_sequence(sequence, config: PipelineConfig, start: int = 0, stop: int | None = None, step: int = 1,
                 progress: bool = True, front_cache: dict[int, StageOutput] | None = None) -> RunResult:
    """Run the pipeline over a sequence (``twohr.dataset.RGBDSequence``). Corrupt frames are skipped
    and counted. ``front_cache`` (frame index -> StageOutput) reuses or collects front-end outputs."""
    from tqdm import tqdm

    pipeline = Pipeline(config, sequence.camera)
    results, stats = [], []
    stop = len(sequence) if stop is None else min(stop, len(sequence))
    t0 = time.perf_counter()
    bar = tqdm(total=len(range(start, stop, step)), disable=not progress, unit="frame", desc=sequence.name,
               dynamic_ncols=True)
    for frame in sequence.frames(start, stop, step):
        front = None if front_cache is None else front_cache.get(frame.index)
        if front is None:
            front = pipeline.front_end(frame)
            if front_cache is not None:
                front_cache[frame.index] = front
        result, row = pipeline.process(frame, front)
        results.append(result)
        stats.append(row)
        bar.set_postfix(status=row.status, kept=row.kept, inliers=row.inliers, refresh=False)
        bar.update(1)
    bar.update(bar.total - bar.n)
    bar.close()
    wall = time.perf_counter() - t0
    online = pipeline.online_trajectory(results)
    refined = pipeline.tracker.trajectory() if results else online
    return RunResult(refined, online, stats, list(sequence.skipped), wall)
