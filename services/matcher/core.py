"""The matcher core: descriptor correspondences between two keypoint sets. Arrays in, matches out.

Baselines live here: mutual nearest neighbour and Lowe's ratio test, for float (L2-normalised)
and packed binary (Hamming) descriptors.
"""

from __future__ import annotations

import numpy as np

from twohr.features import Matches


def descriptor_distances(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """Pairwise distances (Na, Nb): Euclidean for float descriptors, Hamming for packed uint8 bits."""
    if desc_a.dtype == np.uint8:
        bits_a = np.unpackbits(desc_a, axis=1).astype(np.float32)
        bits_b = np.unpackbits(desc_b, axis=1).astype(np.float32)
        # hamming = |a| + |b| - 2 a.b for 0/1 vectors
        return bits_a.sum(1)[:, None] + bits_b.sum(1)[None, :] - 2 * bits_a @ bits_b.T
    a = desc_a.astype(np.float32, copy=False)
    b = desc_b.astype(np.float32, copy=False)
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T
    return np.sqrt(np.maximum(sq, 0))


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


def ratio_test(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8, mutual: bool = True) -> Matches:
    """Lowe's ratio test (nearest / second nearest < ratio), optionally also mutual; score = -distance."""
    if len(desc_a) == 0 or len(desc_b) < 2:
        return Matches.empty()
    dist = descriptor_distances(desc_a, desc_b)
    two = np.argpartition(dist, 1, axis=1)[:, :2]
    d2 = np.take_along_axis(dist, two, 1)
    order = np.argsort(d2, axis=1)
    best = np.take_along_axis(two, order, 1)[:, 0]
    d_sorted = np.take_along_axis(d2, order, 1)
    keep = d_sorted[:, 0] < ratio * d_sorted[:, 1]
    if mutual:
        keep &= dist.argmin(0)[best] == np.arange(len(desc_a))
    idx_a = np.flatnonzero(keep)
    return Matches(idx_a, best[idx_a], (-d_sorted[idx_a, 0]).astype(np.float32))
