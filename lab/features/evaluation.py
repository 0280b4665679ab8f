"""Keypoint quality on RGB-D frame pairs with known geometry: repeatability and match precision.

The ground-truth geometry (reprojection, shared view, correct matches) and its conventions are
:mod:`twohr_lab.pairs`; matches are :func:`twohr.features.mutual_nn`, as the tracker's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from twohr.features import mutual_nn
from twohr_lab.pairs import correct_matches, shared_view


@dataclass
class RepeatabilityResult:
    """Keypoints of A in the shared view; how many have a keypoint of B within the threshold; and how many
    are repeated one-to-one (reprojected A and B keypoints that are each other's nearest neighbour within the
    threshold), which does not reward detectors that pile many keypoints onto the same spots."""

    shared: int
    repeated: int
    repeated_one_to_one: int = 0

    @property
    def ratio(self) -> float:
        return self.repeated / self.shared if self.shared else float("nan")

    @property
    def ratio_one_to_one(self) -> float:
        return self.repeated_one_to_one / self.shared if self.shared else float("nan")


def nearest_neighbours(points: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) from each point to its nearest target and that target's index (inf, -1 without targets)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    if len(targets) == 0 or len(points) == 0:
        return np.full(len(points), np.inf), np.full(len(points), -1, np.int64)
    distances, index = cKDTree(targets).query(points, k=1)
    return distances, index.astype(np.int64)


def clustered_fraction(xy: np.ndarray, radius: float = 3.0) -> float:
    """Fraction of keypoints that have another keypoint of the same image within ``radius`` px.

    High values (stacked pyramid levels, as ORB's) inflate %Rep: a reprojected point then finds *some*
    keypoint nearby even when the pose is wrong.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) < 2:
        return 0.0
    distances, _ = cKDTree(xy).query(xy, k=2)
    return float(np.mean(distances[:, 1] <= radius))


def repeatability(xy_a: np.ndarray, xy_b: np.ndarray, depth_a: np.ndarray, k: np.ndarray, t_b_a: np.ndarray,
                  image_size: tuple[int, int], depth_b: np.ndarray | None = None, threshold: float = 3.0,
                  depth_tolerance: float = 0.05, displacement: tuple[float, float] = (0.0, 0.0)) -> RepeatabilityResult:
    """Keypoints of A that land, reprojected into B, within ``threshold`` px of a keypoint of B,
    out of the keypoints of A in the shared view (see :func:`shared_view`).

    ``displacement`` (px) is added to the reprojections after the shared-view test: with a few times
    the threshold it gives the chance level, the %Rep that keypoint density alone earns.
    """
    projected, visible = shared_view(xy_a, depth_a, k, t_b_a, image_size, depth_b, depth_tolerance)
    points = projected[visible] + np.asarray(displacement, dtype=np.float64)
    distances, nearest_b = nearest_neighbours(points, xy_b)
    close = distances <= threshold
    _, nearest_a = nearest_neighbours(xy_b, points)
    mutual = close & (nearest_a[np.maximum(nearest_b, 0)] == np.arange(len(points)))
    return RepeatabilityResult(int(visible.sum()), int(close.sum()), int(mutual.sum()))


@dataclass
class PrecisionResult:
    """Mutual nearest-neighbour matches of a pair: how many, how many verifiable by depth, how many correct."""

    matches: int
    verifiable: int
    correct: int

    @property
    def ratio(self) -> float:
        return self.correct / self.verifiable if self.verifiable else float("nan")


def match_precision(xy_a: np.ndarray, desc_a: np.ndarray, xy_b: np.ndarray, desc_b: np.ndarray,
                    depth_a: np.ndarray, depth_b: np.ndarray, k: np.ndarray, t_b_a: np.ndarray,
                    threshold: float = 3.0) -> PrecisionResult:
    """The fraction of mutual nearest-neighbour matches that are geometrically correct at ``threshold`` px."""
    matches = mutual_nn(desc_a, desc_b)
    correct, verifiable = correct_matches(xy_a, xy_b, matches.idx_a, matches.idx_b, depth_a, depth_b, k, t_b_a,
                                          threshold)
    return PrecisionResult(len(matches), int(verifiable.sum()), int(correct.sum()))
