"""Ground-truth geometry of RGB-D frame pairs: poses per frame, reprojection, shared view, correct matches.

Every study that scores keypoints or matches against ground truth (the feature table, the matcher's
labels and Table 3) uses these functions. Conventions:

* ``k`` is the 3x3 pinhole matrix; pixel coordinates follow its pixel-centre convention, so an image
  of ``width`` x ``height`` spans [-0.5, width - 0.5] x [-0.5, height - 0.5];
* ``t_b_a`` is the 4x4 rigid transform from camera A's frame into camera B's,
  ``inv(T_w_b) @ T_w_a`` for camera-to-world poses (:func:`relative_pose`);
* a keypoint's depth is read at its nearest pixel (:func:`twohr.geometry.depth_at_pixels`), NaN where
  there is no reading: interpolating across a depth edge would invent a surface between a person and
  the wall behind.

Ground truth assumes a static world: keypoints on moving people reproject to where a static point
would be, so they count as not repeated and their matches as wrong.
"""

from __future__ import annotations

import numpy as np

from twohr.errors import DatasetError
from twohr.geometry import backproject, depth_at_pixels, invert_pose, project, transform_points
from twohr.trajectory import interpolate_poses


def frame_poses(sequence) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world ground-truth poses (F, 4, 4) at every frame's stamp and their validity (F,), through
    the sequence's default ground-truth extrinsic (``twohr.dataset.RGBDSequence``)."""
    if not sequence.has_ground_truth():
        raise DatasetError(f"{sequence.root} has no groundtruth.txt: this study needs ground-truth poses")
    return interpolate_poses(sequence.ground_truth(sequence.default_gt_extrinsic()), sequence.stamps)


def relative_pose(t_w_a: np.ndarray, t_w_b: np.ndarray) -> np.ndarray:
    """``T_b_a = inv(T_w_b) @ T_w_a``: maps points from camera A's frame into camera B's."""
    return invert_pose(t_w_b) @ t_w_a


def project_into(xy_a: np.ndarray, z_a: np.ndarray, k: np.ndarray, t_b_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``xy_a`` (N, 2) at depths ``z_a`` (N,) seen from camera B: ``(xy_b (N, 2), z_b (N,))``, NaN where
    ``z_a`` is NaN."""
    xy_a = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)
    z_a = np.asarray(z_a, dtype=np.float64)
    points_b = transform_points(t_b_a, backproject(xy_a, np.nan_to_num(z_a, nan=0.0), k))
    points_b[~np.isfinite(z_a)] = np.nan
    with np.errstate(invalid="ignore"):
        return project(points_b, k), points_b[:, 2]


def in_image(xy: np.ndarray, z: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: in front of the camera and inside a ``width`` x ``height`` image."""
    with np.errstate(invalid="ignore"):
        return (np.isfinite(xy).all(axis=1) & (z > 0) & (xy[:, 0] >= -0.5) & (xy[:, 0] <= width - 0.5)
                & (xy[:, 1] >= -0.5) & (xy[:, 1] <= height - 0.5))


def depth_agrees(predicted: np.ndarray, measured: np.ndarray, tolerance: float) -> np.ndarray:
    """|predicted - measured| <= tolerance * measured (relative, since depth noise grows with range)."""
    with np.errstate(invalid="ignore"):
        return np.abs(predicted - measured) <= tolerance * measured


def reproject(xy_a: np.ndarray, depth_a: np.ndarray, k: np.ndarray, t_b_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where keypoints of A land in B: ``(xy_b (N, 2), valid (N,))``.

    ``valid`` is False where A's depth map has no reading at the keypoint or the point ends up
    behind camera B (then ``xy_b`` is NaN). It says nothing about B's image bounds: see :func:`shared_view`.
    """
    xy_a = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)
    xy_b, z_b = project_into(xy_a, depth_at_pixels(depth_a, xy_a), k, t_b_a)
    with np.errstate(invalid="ignore"):
        return xy_b, np.isfinite(xy_b).all(axis=1) & (z_b > 0)


def shared_view(xy_a: np.ndarray, depth_a: np.ndarray, k: np.ndarray, t_b_a: np.ndarray,
                image_size: tuple[int, int], depth_b: np.ndarray | None = None,
                depth_tolerance: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of A that camera B sees: ``(xy_b, visible)``.

    Visible means: A has depth at the keypoint, its reprojection lies inside B's ``image_size``
    = (width, height), and, when ``depth_b`` is given, B's depth there agrees with the
    reprojected depth within ``depth_tolerance`` (relative). The depth check removes points that
    are occluded in B and points on objects that moved between the frames.
    """
    xy_a = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)
    xy_b, z_b = project_into(xy_a, depth_at_pixels(depth_a, xy_a), k, t_b_a)
    visible = in_image(xy_b, z_b, *image_size)
    if depth_b is not None:
        with np.errstate(invalid="ignore"):
            visible &= np.abs(depth_at_pixels(depth_b, xy_b) - z_b) <= depth_tolerance * z_b
    return xy_b, visible


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
