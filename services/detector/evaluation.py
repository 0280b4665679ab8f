"""Keypoint quality on RGB-D frame pairs with known geometry: reprojection, repeatability, match precision.

Plain numpy functions, reusable by any service. Conventions:

* ``k`` is the 3x3 pinhole matrix, pixel coordinates follow its pixel-centre convention;
* ``t_b_a`` is the 4x4 rigid transform from camera A's frame into camera B's,
  ``inv(T_w_b) @ T_w_a`` for camera-to-world poses ``T_w_a``, ``T_w_b``;
* depth maps are (H, W) float metres with 0 (or NaN) where there is no reading; a keypoint's
  depth is read at its nearest pixel, never interpolated, because interpolating across a depth
  edge would invent a surface between a person and the wall behind.

Ground truth assumes a static world: keypoints on moving people reproject to where a static
point would be, so they count as not repeated and their matches as wrong. That is intended: on
dynamic scenes such keypoints *are* harmful to a tracker.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from twohr.geometry import backproject, depth_at_pixels, invert_pose, project, transform_points


def reproject(xy_a: np.ndarray, depth_a: np.ndarray, k: np.ndarray, t_b_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where keypoints of A land in B: ``(xy_b (N, 2), valid (N,))``.

    ``valid`` is False where A's depth map has no reading at the keypoint or the point ends up
    behind camera B (then ``xy_b`` is NaN). It says nothing about B's image bounds: see
    :func:`shared_view`.
    """
    xy_b, z_b = _reproject_with_depth(xy_a, depth_a, k, t_b_a)
    return xy_b, np.isfinite(xy_b).all(axis=1) & (z_b > 0)


def _reproject_with_depth(xy_a: np.ndarray, depth_a: np.ndarray, k: np.ndarray,
                          t_b_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xy_a = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)
    z_a = depth_at_pixels(depth_a, xy_a)
    points_b = transform_points(t_b_a, backproject(xy_a, np.nan_to_num(z_a, nan=0.0), k))
    points_b[~np.isfinite(z_a)] = np.nan
    with np.errstate(invalid="ignore"):
        return project(points_b, k), points_b[:, 2]


def shared_view(xy_a: np.ndarray, depth_a: np.ndarray, k: np.ndarray, t_b_a: np.ndarray,
                image_size: tuple[int, int], depth_b: np.ndarray | None = None,
                depth_tolerance: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of A that camera B sees: ``(xy_b, visible)``.

    Visible means: A has depth at the keypoint, its reprojection lies inside B's ``image_size``
    = (width, height), and, when ``depth_b`` is given, B's depth there agrees with the
    reprojected depth within ``depth_tolerance`` (relative). The depth check removes points that
    are occluded in B and points on objects that moved between the frames.
    """
    width, height = image_size
    xy_b, z_b = _reproject_with_depth(xy_a, depth_a, k, t_b_a)
    with np.errstate(invalid="ignore"):
        visible = (np.isfinite(xy_b).all(axis=1) & (z_b > 0) & (xy_b[:, 0] >= -0.5) & (xy_b[:, 0] <= width - 0.5)
                   & (xy_b[:, 1] >= -0.5) & (xy_b[:, 1] <= height - 0.5))
        if depth_b is not None:
            seen = depth_at_pixels(depth_b, xy_b)
            visible &= np.abs(seen - z_b) <= depth_tolerance * z_b
    return xy_b, visible


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


def correct_matches(xy_a: np.ndarray, xy_b: np.ndarray, idx_a: np.ndarray, idx_b: np.ndarray,
                    depth_a: np.ndarray, depth_b: np.ndarray, k: np.ndarray, t_b_a: np.ndarray,
                    threshold: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Which matches ``(idx_a[i], idx_b[i])`` are geometrically correct: ``(correct (M,), verifiable (M,))``.

    A match is checked A->B with A's depth (reprojection error <= ``threshold`` px); where A has no
    depth, B->A with B's depth. A match with depth in neither frame is not verifiable and never correct.
    """
    idx_a = np.asarray(idx_a, dtype=np.int64)
    idx_b = np.asarray(idx_b, dtype=np.int64)
    pa = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)[idx_a]
    pb = np.asarray(xy_b, dtype=np.float64).reshape(-1, 2)[idx_b]
    a_in_b, valid_ab = reproject(pa, depth_a, k, t_b_a)
    b_in_a, valid_ba = reproject(pb, depth_b, k, invert_pose(t_b_a))
    with np.errstate(invalid="ignore"):
        error = np.where(valid_ab, np.linalg.norm(a_in_b - pb, axis=1), np.linalg.norm(b_in_a - pa, axis=1))
    verifiable = valid_ab | valid_ba
    return verifiable & (error <= threshold), verifiable


def mutual_nn_matches(desc_a: np.ndarray, desc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest-neighbour descriptor matches ``(idx_a, idx_b)``, sorted by ``idx_a``: Hamming for packed
    uint8 descriptors, Euclidean otherwise."""
    if len(desc_a) == 0 or len(desc_b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if desc_a.dtype == np.uint8:
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        matches = matcher.match(np.ascontiguousarray(desc_a), np.ascontiguousarray(desc_b))
        idx_a = np.array([m.queryIdx for m in matches], np.int64)
        idx_b = np.array([m.trainIdx for m in matches], np.int64)
        order = np.argsort(idx_a, kind="stable")
        return idx_a[order], idx_b[order]
    a = np.asarray(desc_a, dtype=np.float32)
    b = np.asarray(desc_b, dtype=np.float32)
    # squared distances up to a per-row constant of A: enough for both arg-minima
    distance = (b * b).sum(1)[None, :] - 2 * a @ b.T
    nearest_b = distance.argmin(1)
    nearest_a = (distance + (a * a).sum(1)[:, None]).argmin(0)
    idx_a = np.flatnonzero(nearest_a[nearest_b] == np.arange(len(a)))
    return idx_a, nearest_b[idx_a]


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
    idx_a, idx_b = mutual_nn_matches(desc_a, desc_b)
    correct, verifiable = correct_matches(xy_a, xy_b, idx_a, idx_b, depth_a, depth_b, k, t_b_a, threshold)
    return PrecisionResult(len(idx_a), int(verifiable.sum()), int(correct.sum()))


def relative_pose(t_w_a: np.ndarray, t_w_b: np.ndarray) -> np.ndarray:
    """``T_b_a = inv(T_w_b) @ T_w_a``: maps points from camera A's frame into camera B's."""
    return invert_pose(t_w_b) @ t_w_a
