"""The keyframe policy: when the map needs a keyframe, read from the tracking's own evidence, and which waiting
keyframe jobs a newer one makes redundant.

As ORB-SLAM3's ``Tracking::NeedNewKeyFrame``, for RGB-D:

- a frame is **weak** when its inlier tracks fall below ``keyframe_tracked_ratio`` of those its reference keyframe
  gave it, or its close ones (depth nearer than ``keyframe_close_depth_m``) do: far points can stay in view while
  the near ones, which pin translation best, leave it; a weak frame asks for a keyframe. ORB-SLAM3 counts close
  points against a fixed 100 with 70 untracked ones to gain; optical flow follows fewer points than its keypoints
  (a median of 64 close inliers on the dev frames), so the close points are measured against the reference too;
- **time**: a frame also asks when the latest keyframe job is ``keyframe_max_interval_s`` old; and a weak frame
  waits behind a busy mapping worker (it is queued) only then, or when tracking is very weak (below a quarter of
  the reference); otherwise the next weak frame asks again once the worker is free;
- the job decides: where a keyframe of the local map holds the frame's view already (the frame tracks
  ``keyframe_tracked_ratio`` of its landmarks) it adds none. A camera that holds still, or comes back to a place the
  map holds, adds no keyframes: density follows the scene, not the CPU.

Culling is the map's: landmarks no other keyframe found again (:meth:`~.map.Map.retire_unconfirmed`), then keyframes
the others make redundant (:meth:`~.map.Map.cull_redundant`). Plain values in, plain values out: the schedules call
this module.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from twohr.config import TrackerConfig

Job = TypeVar("Job")

VERY_WEAK = 0.25
"""a frame tracking less than this share of its reference queues its keyframe at once (ORB-SLAM3's c1c)"""


@dataclass(frozen=True)
class Evidence:
    """What one tracked frame says about the map it was tracked against."""

    inliers: int
    """the frame's inlier tracks"""
    reference: int
    """the inlier tracks of the first frame tracked after the latest keyframe (0: none yet)"""
    close: int
    """inliers with depth nearer than ``keyframe_close_depth_m``"""
    reference_close: int
    """the same frame's close inliers"""
    seconds_since_keyframe: float

    @classmethod
    def of(cls, inliers: int, depth: np.ndarray | None, reference: tuple[int, int], seconds: float,
           conf: TrackerConfig) -> Evidence:
        """Evidence from a frame's ``inliers``, their measured ``depth`` (m, 0 = none) and the reference's
        (inliers, close inliers)."""
        return cls(inliers, reference[0], close_points(depth, conf), reference[1], seconds)


def close_points(depth: np.ndarray | None, conf: TrackerConfig) -> int:
    """How many of the depths (m, 0 = none) are close (nearer than ``keyframe_close_depth_m``)."""
    return 0 if depth is None else int(((depth > 0) & (depth < conf.keyframe_close_depth_m)).sum())


def weakness(evidence: Evidence, conf: TrackerConfig) -> str | None:
    """Why the frame asks for a keyframe job (None: it does not). The job decides: where a keyframe of the map holds
    the frame's view already it adds none (:meth:`~.mapping.LocalMapping.covering_keyframe`)."""
    if evidence.inliers < conf.keyframe_tracked_ratio * evidence.reference:
        return f"{evidence.inliers} inlier tracks of the reference keyframe's {evidence.reference}"
    # close points count once the reference has a pose's worth of them (min_inliers): a handful rises and falls
    if evidence.reference_close >= conf.min_inliers and (
            evidence.close < conf.keyframe_tracked_ratio * evidence.reference_close):
        return (f"{evidence.close} inliers nearer than {conf.keyframe_close_depth_m} m of the reference keyframe's "
                f"{evidence.reference_close}")
    if evidence.seconds_since_keyframe >= conf.keyframe_max_interval_s:
        return f"the latest keyframe job is {evidence.seconds_since_keyframe:.1f} s old"
    return None


def may_queue(evidence: Evidence, conf: TrackerConfig) -> bool:
    """Whether a weak frame's keyframe job waits behind a busy mapping worker (else a later frame asks again)."""
    return (evidence.seconds_since_keyframe >= conf.keyframe_max_interval_s
            or evidence.inliers < VERY_WEAK * evidence.reference)


def redundant(older: np.ndarray | None, newer: np.ndarray | None, conf: TrackerConfig) -> bool:
    """Whether a waiting keyframe job that tracks landmarks ``older`` is made redundant by a newer job tracking
    ``newer`` (None: the camera was lost, the job relocalises): the newer frame still tracks at least
    ``keyframe_tracked_ratio`` of the older one's landmarks, so it maps the same view, later. A waiting lost job is
    redundant behind any newer job (the newest look for the camera wins, or the camera tracks again); a tracked one
    is never redundant behind a lost one (it maps the view before the loss)."""
    if older is None or newer is None:
        return older is None
    if len(older) == 0:
        return True
    return float(np.isin(older, newer).mean()) >= conf.keyframe_tracked_ratio


class KeyframeQueue(Generic[Job]):
    """Keyframe jobs waiting for a busy mapping worker, oldest first: a short CPU sheds stale work, not density.

    :meth:`push` drops every waiting job that the new one makes :func:`redundant`, then, over ``capacity``, the
    oldest; never the newest. ``shed`` counts the jobs dropped."""

    def __init__(self, capacity: int, conf: TrackerConfig) -> None:
        self.capacity = capacity
        self.conf = conf
        self._waiting: list[tuple[Job, np.ndarray | None]] = []
        self.shed = 0

    def __len__(self) -> int:
        return len(self._waiting)

    def push(self, job: Job, landmarks: np.ndarray | None) -> None:
        """Queue ``job``, whose frame tracks ``landmarks`` (None: a lost frame)."""
        kept = [(old, seen) for old, seen in self._waiting if not redundant(seen, landmarks, self.conf)]
        kept.append((job, landmarks))
        kept = kept[-self.capacity:]
        self.shed += len(self._waiting) + 1 - len(kept)
        self._waiting = kept

    def landmarks(self) -> list[np.ndarray]:
        """The landmarks the waiting jobs' frames track."""
        return [seen for _, seen in self._waiting if seen is not None]

    def pop(self) -> Job | None:
        """The oldest waiting job (None: none waits)."""
        return self._waiting.pop(0)[0] if self._waiting else None

    def clear(self) -> None:
        self._waiting = []
