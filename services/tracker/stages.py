"""What a schedule is given (the :class:`Stages`, where the networks run) and what it reports per frame
(:class:`FrameStats`) and per keyframe job (:class:`KeyframeLog`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from twohr.dataset import Frame
from twohr.features import Keypoints, Matches


@dataclass
class Stages:
    """Where the networks of a schedule run: in this process (``twohr_app.pipeline.local_stages``) or in the
    detector, yolo and matcher services, asked over the bus (the tracker service builds those). Every stage takes
    the :class:`~twohr.dataset.Frame` it works for: a local stage reads its images, a remote one sends its
    message and names it in the request."""

    detect: Callable[[Frame], Keypoints]
    """frame -> the frame's 2HR keypoints"""
    dynamic_mask: Callable[[Frame], tuple[np.ndarray, int]] | None
    """frame -> (the frame's dynamic mask, True = moving; how many dynamic objects), or None = no masking"""
    match: Callable[[Frame, np.ndarray, np.ndarray], Matches]
    """(frame, its descriptors, the map's descriptors) -> Matches"""
    chosen: dict[str, float] = field(default_factory=dict)
    """settings the stages chose for this camera at warm-up (the detector's input scale), for the run's summary"""
    match_sets: Callable[[Frame, np.ndarray, list[np.ndarray]], list[Matches]] | None = None
    """(frame, its descriptors, several reference sets) -> Matches per set, in one query; None: :attr:`match` per
    set (in process, where a call costs no round trip)"""

    def matcher_for(self, frame: Frame) -> FrameMatch:
        """The match stage bound to ``frame``, as the tracker's match function."""
        return FrameMatch(self, frame)


@dataclass
class FrameMatch:
    """The match stage for one frame: called with one reference set, or :meth:`sets` with several (one query to a
    matcher service where the stages offer it, see :func:`twohr.pose.match_each`)."""

    stages: Stages
    frame: Frame

    def __call__(self, desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
        return self.stages.match(self.frame, desc_a, desc_b)

    def sets(self, desc_a: np.ndarray, sets: list[np.ndarray]) -> list[Matches]:
        if self.stages.match_sets is None:
            return [self(desc_a, desc_b) for desc_b in sets]
        return self.stages.match_sets(self.frame, desc_a, sets)


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
    mask_age: int = -1
    """frames since the YOLO detection behind this frame's mask (-1: no mask)"""


@dataclass
class KeyframeLog:
    """What one keyframe job cost and how late its map arrived (``lag_frames``), for the bench."""

    index: int
    status: str
    keyframe: bool
    keypoints: int
    kept: int
    ms_detector: float
    ms_yolo: float
    ms_mapping: float
    lag_frames: int = 0
    kind: str = "2hr"
    """``2hr``: detection and matching on the keyframe; ``tracked``: a keyframe from the optical-flow tracks and new
    corners, no network; ``describe``: 2HR detection of an earlier tracked keyframe joined to the map; ``loop``: a
    verified loop closed (:mod:`.loops`)"""
    ms_job: float = 0.0
    """the job's whole latency on the mapping worker, every stage it asked (over the bus or in process) included"""


def keyframe_job_latency(log: list[KeyframeLog]) -> dict[str, float]:
    """Median and 90th percentile of the keyframe jobs' whole latency (ms), and their count."""
    ms = [job.ms_job for job in log]
    if not ms:
        return {"count": 0}
    return {"count": len(ms), "ms_job_median": round(float(np.median(ms)), 2),
            "ms_job_p90": round(float(np.percentile(ms, 90)), 2)}
