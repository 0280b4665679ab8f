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


def descriptor_distances(desc_a: np.ndarray, desc_b: np.ndarray, squared: bool = False) -> np.ndarray:
    """Pairwise distances (Na, Nb): Euclidean (``squared``: its square) for float descriptors, Hamming for
    packed uint8 bits."""
    if desc_a.dtype == np.uint8:
        bits_a = np.unpackbits(desc_a, axis=1).astype(np.float32)
        bits_b = np.unpackbits(desc_b, axis=1).astype(np.float32)
        # hamming = |a| + |b| - 2 a.b for 0/1 vectors
        return bits_a.sum(1)[:, None] + bits_b.sum(1)[None, :] - 2 * bits_a @ bits_b.T
    a = desc_a.astype(np.float32, copy=False)
    b = desc_b.astype(np.float32, copy=False)
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T
    return sq if squared else np.sqrt(np.maximum(sq, 0))


def mutual_nn(desc_a: np.ndarray, desc_b: np.ndarray, max_distance: float | None = None) -> Matches:
    """Pairs that are each other's nearest neighbour; score = -distance."""
    if len(desc_a) == 0 or len(desc_b) == 0:
        return Matches.empty()
    dist = descriptor_distances(desc_a, desc_b)
    nn_ab = dist.argmin(1)
    nn_ba = dist.argmin(0)
    idx_a = np.flatnonzero(nn_ba[nn_ab] == np.arange(len(desc_a)))
    idx_b = nn_ab[idx_a]
    d = dist[idx_a, idx_b]
    if max_distance is not None:
        keep = d <= max_distance
        idx_a, idx_b, d = idx_a[keep], idx_b[keep], d[keep]
    return Matches(idx_a, idx_b, (-d).astype(np.float32))
