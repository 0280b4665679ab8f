"""In-process data contracts between the cores: keypoints, detections and matches.

These are plain dataclasses of numpy arrays. The bus messages (``twohr.messages``) carry the
same arrays across Zenoh.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Keypoints:
    """Keypoints of one image.

    ``xy`` (N, 2) float32 pixel coordinates in the original image (x right, y down);
    ``descriptors`` (N, D): float32 L2-normalised (R2D2, D=128) or uint8 packed bits (ORB, D=32);
    ``scores`` (N,) float32, higher is better; ``reliability`` and ``repeatability`` (N,) float32
    where the detector provides them (NaN otherwise).
    """

    xy: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray
    reliability: np.ndarray | None = None
    repeatability: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xy)

    @property
    def binary(self) -> bool:
        """True for packed binary descriptors, matched by Hamming distance."""
        return self.descriptors.dtype == np.uint8

    def subset(self, keep: np.ndarray) -> Keypoints:
        """The keypoints selected by a boolean mask or index array."""
        def pick(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else values[keep]

        return Keypoints(self.xy[keep], self.descriptors[keep], self.scores[keep],
                         pick(self.reliability), pick(self.repeatability))

    @classmethod
    def empty(cls, dim: int = 128, binary: bool = False) -> Keypoints:
        dtype = np.uint8 if binary else np.float32
        return cls(np.zeros((0, 2), np.float32), np.zeros((0, dim), dtype), np.zeros(0, np.float32))


@dataclass
class Detections:
    """Object detections of one image: ``boxes`` (N, 4) x1 y1 x2 y2 in image pixels, ``scores`` (N,),
    ``class_ids`` (N,) int, and ``names`` the class name of each detection."""

    boxes: np.ndarray
    scores: np.ndarray
    class_ids: np.ndarray
    names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def empty(cls) -> Detections:
        return cls(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64), [])


@dataclass
class Matches:
    """Correspondences between keypoint sets A and B: ``idx_a``, ``idx_b`` (M,) int and ``scores`` (M,),
    higher is more confident."""

    idx_a: np.ndarray
    idx_b: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return len(self.idx_a)

    @classmethod
    def empty(cls) -> Matches:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))


def drop_masked(keypoints: Keypoints, mask: np.ndarray) -> Keypoints:
    """The keypoints whose nearest pixel is outside ``mask`` (H, W) bool; positions are clamped to the image."""
    if len(keypoints) == 0:
        return keypoints
    return keypoints.subset(~masked(keypoints.xy, mask))


def masked(xy: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N,) bool: True where the nearest pixel of each point is set in ``mask``."""
    height, width = mask.shape
    cols = np.clip(np.rint(xy[:, 0]).astype(np.int64), 0, width - 1)
    rows = np.clip(np.rint(xy[:, 1]).astype(np.int64), 0, height - 1)
    return mask[rows, cols]
