"""Pose estimation of one view against known 3-D points: projection, depth sampling, the residuals (shared with
:mod:`.bundle_adjustment` and the lab's consistency check), RANSAC PnP, pose refinement and their combination
(:func:`estimate_pose`). Pure functions on numpy arrays.

Conventions: ``T_cw`` maps world points into the camera (x right, y down, z forward); ``T_wc`` is its
inverse, the camera-to-world pose that the tracker reports. Every residual is expressed in units of
one pixel of reprojection noise, so a single robust (Huber) scale applies to all of them:

* reprojection ``(u - u_meas, v - v_meas)`` in pixels;
* depth ``(1/z - 1/z_meas) / depth_noise`` where the sensor's depth noise grows as
  ``depth_noise * z**2`` (structured light and ToF sensors behave so): an inverse-depth error
  (:func:`depth_residual`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from twohr.features import Matches
from twohr.geometry import (
    huber_weights,
    invert_pose,
    rotation_angle,
    skew,
    so3_exp_batch,
    so3_log,
    transform_points,
)

MatchFn = Callable[[np.ndarray, np.ndarray], Matches]
"""(descriptors_a, descriptors_b) -> Matches; injected so the tracker does not depend on the matcher service. A
match function may also offer ``sets(descriptors_a, [descriptors_b, ...]) -> [Matches, ...]``, answering several
reference sets in one call (one query to a matcher service), see :func:`match_each`."""


def match_each(match: MatchFn, descriptors: np.ndarray, sets: list[np.ndarray]) -> list[Matches]:
    """The matches of ``descriptors`` against each reference set: in one call where ``match`` offers ``sets``, else
    one call per set (the same matches either way)."""
    if not sets:
        return []
    batched = getattr(match, "sets", None)
    return batched(descriptors, sets) if batched is not None else [match(descriptors, b) for b in sets]

# ----------------------------------------------------------------------------- SE(3) helpers


def pose_from_vectors(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """A 4x4 transform from an OpenCV rotation vector and translation."""
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]
    pose[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return pose


def pose_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) between two camera-to-world poses."""
    rel = invert_pose(a) @ b
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(rotation_angle(rel[:3, :3])))


def scale_motion(rel: np.ndarray, factor: float) -> np.ndarray:
    """A relative motion scaled by ``factor`` (rotation angle and translation), for motion extrapolation."""
    out = np.eye(4)
    out[:3, :3] = so3_exp_batch(so3_log(rel[:3, :3]) * factor)
    out[:3, 3] = rel[:3, 3] * factor
    return out


def apply_update(T_cw: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Left update on the camera side: X_c = exp(omega) (R X + t) + upsilon, delta = (omega, upsilon)."""
    out = np.eye(4)
    rot = so3_exp_batch(delta[:3])
    out[:3, :3] = rot @ T_cw[:3, :3]
    out[:3, 3] = rot @ T_cw[:3, 3] + delta[3:6]
    return out


# ----------------------------------------------------------------------------- camera


def sample_depth(depth: np.ndarray, xy: np.ndarray, min_depth: float, max_depth: float,
                 edge_ratio: float) -> np.ndarray:
    """Depth (N,) at the nearest pixel of each keypoint, 0 where there is no trustworthy reading.

    A reading is rejected outside [min_depth, max_depth] and on depth edges: where the valid readings
    of the 3x3 neighbourhood spread by more than ``edge_ratio * z`` (colour and depth disagree there,
    and a point on an object boundary jumps between foreground and background).
    """
    if len(xy) == 0:
        return np.zeros(0)
    height, width = depth.shape
    u = np.clip(np.rint(xy[:, 0]).astype(np.int64), 0, width - 1)
    v = np.clip(np.rint(xy[:, 1]).astype(np.int64), 0, height - 1)
    offsets = np.array([-1, 0, 1])
    rows = np.clip(v[:, None, None] + offsets[None, :, None], 0, height - 1)
    cols = np.clip(u[:, None, None] + offsets[None, None, :], 0, width - 1)
    patch = depth[rows, cols].reshape(len(xy), 9).astype(np.float64)
    z = patch[:, 4]
    valid = (z >= min_depth) & (z <= max_depth) & np.isfinite(z)
    has = patch > 0
    hi = np.where(has, patch, -np.inf).max(1)
    lo = np.where(has, patch, np.inf).min(1)
    valid &= (hi - lo) <= edge_ratio * z
    return np.where(valid, z, 0.0)


# ----------------------------------------------------------------------------- residuals


def _depth_slope(inv_z: np.ndarray, has_depth: np.ndarray, depth_noise: float) -> np.ndarray:
    """Derivative of :func:`depth_residual` with respect to the predicted depth z, given ``inv_z = 1 / z``."""
    return np.where(has_depth, -(inv_z**2) / depth_noise, 0.0)


def depth_residual(inv_z: np.ndarray, z_meas: np.ndarray, depth_noise: float) -> tuple[np.ndarray, np.ndarray]:
    """The depth residual ``(1/z - 1/z_meas) / depth_noise`` of predicted inverse depths ``inv_z = 1 / z`` against
    measured depths ``z_meas`` (0 = no reading: residual and slope 0), in units of one pixel of reprojection noise,
    and its derivative with respect to z."""
    has_depth = z_meas > 0
    with np.errstate(divide="ignore"):
        res = np.where(has_depth, (inv_z - 1.0 / np.where(has_depth, z_meas, 1.0)) / depth_noise, 0.0)
    return res, _depth_slope(inv_z, has_depth, depth_noise)


def observation_residuals(K: np.ndarray, points_cam: np.ndarray, xy: np.ndarray, z_meas: np.ndarray,
                          depth_noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 3) of observations (u, v, inverse depth; the last is 0 without a depth reading) and
    their Jacobians (N, 3, 3) with respect to the camera-frame point."""
    x, y, z = points_cam[:, 0], points_cam[:, 1], points_cam[:, 2]
    z = np.where(np.abs(z) < 1e-9, 1e-9, z)
    fx, fy = K[0, 0], K[1, 1]
    inv_z = 1.0 / z
    res = np.empty((len(points_cam), 3))
    res[:, 0] = fx * x * inv_z + K[0, 2] - xy[:, 0]
    res[:, 1] = fy * y * inv_z + K[1, 2] - xy[:, 1]
    res[:, 2], depth_slope = depth_residual(inv_z, z_meas, depth_noise)
    jac = np.zeros((len(points_cam), 3, 3))
    jac[:, 0, 0] = fx * inv_z
    jac[:, 0, 2] = -fx * x * inv_z**2
    jac[:, 1, 1] = fy * inv_z
    jac[:, 1, 2] = -fy * y * inv_z**2
    jac[:, 2, 2] = depth_slope
    return res, jac


def pose_jacobian(K: np.ndarray, points_cam: np.ndarray, has_depth: np.ndarray, depth_noise: float) -> np.ndarray:
    """Jacobians (N, 3, 6) of the residuals of :func:`observation_residuals` with respect to a left pose update
    ``delta = (omega, upsilon)`` (X_c -> exp(omega) X_c + upsilon), written out element by element."""
    x, y, z = points_cam[:, 0], points_cam[:, 1], points_cam[:, 2]
    z = np.where(np.abs(z) < 1e-9, 1e-9, z)
    fx, fy = K[0, 0], K[1, 1]
    xz, yz, inv_z = x / z, y / z, 1.0 / z
    jac = np.zeros((len(points_cam), 3, 6))
    jac[:, 0, 0] = -fx * xz * yz
    jac[:, 0, 1] = fx * (1 + xz * xz)
    jac[:, 0, 2] = -fx * yz
    jac[:, 0, 3] = fx * inv_z
    jac[:, 0, 5] = -fx * xz * inv_z
    jac[:, 1, 0] = -fy * (1 + yz * yz)
    jac[:, 1, 1] = fy * xz * yz
    jac[:, 1, 2] = fy * xz
    jac[:, 1, 4] = fy * inv_z
    jac[:, 1, 5] = -fy * yz * inv_z
    depth_term = _depth_slope(inv_z, has_depth, depth_noise)
    jac[:, 2, 0] = depth_term * y
    jac[:, 2, 1] = -depth_term * x
    jac[:, 2, 5] = depth_term
    return jac


def observation_errors(K: np.ndarray, T_cw: np.ndarray, points_w: np.ndarray, xy: np.ndarray,
                       z_meas: np.ndarray, depth_noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection error (px) and absolute depth residual (pixel-noise units) of each observation."""
    res, _ = observation_residuals(K, transform_points(T_cw, points_w), xy, z_meas, depth_noise)
    behind = transform_points(T_cw, points_w)[:, 2] <= 0
    reproj = np.where(behind, np.inf, np.hypot(res[:, 0], res[:, 1]))
    return reproj, np.abs(res[:, 2])


def inliers_of(K: np.ndarray, T_cw: np.ndarray, points_w: np.ndarray, xy: np.ndarray, z_meas: np.ndarray,
               threshold_px: float, depth_noise: float) -> np.ndarray:
    """The observations whose reprojection error and depth residual (see :func:`observation_errors`) are both under
    ``threshold_px``."""
    reproj, depth_err = observation_errors(K, T_cw, points_w, xy, z_meas, depth_noise)
    return (reproj < threshold_px) & (depth_err < threshold_px)


# ----------------------------------------------------------------------------- PnP and pose refinement


def pnp_ransac(K: np.ndarray, points_w: np.ndarray, xy: np.ndarray, threshold_px: float, iterations: int,
               confidence: float = 0.999) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC PnP (AP3P minimal solver): ``(T_cw or None, inlier mask)``. Deterministic for given inputs."""
    inlier_mask = np.zeros(len(points_w), bool)
    if len(points_w) < 4:
        return None, inlier_mask
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            np.ascontiguousarray(points_w, np.float64), np.ascontiguousarray(xy, np.float64), K, None,
            iterationsCount=iterations, reprojectionError=threshold_px, confidence=confidence,
            flags=cv2.SOLVEPNP_AP3P)
    except cv2.error:
        return None, inlier_mask
    if not ok or inliers is None or len(inliers) < 4:
        return None, inlier_mask
    inlier_mask[inliers.reshape(-1)] = True
    return pose_from_vectors(rvec, tvec), inlier_mask


def matched_pnp(K: np.ndarray, match, descriptors: np.ndarray, xy: np.ndarray, map_descriptors: np.ndarray,
                map_positions: np.ndarray, min_matches: int, threshold_px: float, iterations: int):
    """Descriptor matches of a view's keypoints (``descriptors``, ``xy``) to map points, then RANSAC PnP on them:
    ``(T_cw or None, keypoint index, map point index, inlier mask)`` per match; None when fewer than
    ``min_matches`` match (relocalisation and loop verification both start this way)."""
    return pnp_on_matches(K, match(descriptors, map_descriptors), xy, map_positions, min_matches, threshold_px,
                          iterations)


def pnp_on_matches(K: np.ndarray, matches: Matches, xy: np.ndarray, map_positions: np.ndarray, min_matches: int,
                   threshold_px: float, iterations: int):
    """RANSAC PnP on matches already found (see :func:`matched_pnp`)."""
    if len(matches) < min_matches:
        return None
    a, b = np.asarray(matches.idx_a, np.int64), np.asarray(matches.idx_b, np.int64)
    T_cw, inliers = pnp_ransac(K, map_positions[b], xy[a], threshold_px, iterations)
    return T_cw, a, b, inliers


@dataclass
class MotionPrior:
    """A Gaussian prior on the pose: the motion model's prediction with per-frame standard deviations."""

    T_cw: np.ndarray
    sigma_translation: float
    sigma_rotation_rad: float


def refine_pose(K: np.ndarray, T_cw: np.ndarray, points_w: np.ndarray, xy: np.ndarray, z_meas: np.ndarray,
                depth_noise: float, huber: float, iterations: int = 8,
                prior: MotionPrior | None = None) -> np.ndarray:
    """Pose-only Gauss-Newton with Huber weights (IRLS) on reprojection + inverse-depth residuals.

    The optional motion prior adds six residuals (rotation and translation away from the prediction,
    divided by their sigmas), so a frame with few observations leans on the motion model.
    """
    T = T_cw.copy()
    if len(points_w) == 0 and prior is None:
        return T
    for _ in range(iterations):
        pc = transform_points(T, points_w)
        res, _ = observation_residuals(K, pc, xy, z_meas, depth_noise)
        jac = pose_jacobian(K, pc, z_meas > 0, depth_noise).reshape(-1, 6)
        r = res.reshape(-1)
        if prior is not None:
            err = T @ invert_pose(prior.T_cw)
            r_prior = np.concatenate([so3_log(err[:3, :3]) / prior.sigma_rotation_rad,
                                      err[:3, 3] / prior.sigma_translation])
            j_prior = np.zeros((6, 6))
            j_prior[:3, :3] = np.eye(3) / prior.sigma_rotation_rad
            j_prior[3:, :3] = -skew(err[:3, 3]) / prior.sigma_translation
            j_prior[3:, 3:] = np.eye(3) / prior.sigma_translation
            r = np.concatenate([r, r_prior])
            jac = np.concatenate([jac, j_prior])
        weights = huber_weights(r, huber)
        hessian = jac.T @ (jac * weights[:, None])
        gradient = jac.T @ (weights * r)
        try:
            delta = -np.linalg.solve(hessian + 1e-9 * np.eye(6), gradient)
        except np.linalg.LinAlgError:
            break
        T = apply_update(T, delta)
        if np.abs(delta).max() < 1e-5:  # 10 micro-radians and 10 micrometres: far below the noise
            break
    return T


def estimate_pose(K: np.ndarray, points_w: np.ndarray, xy: np.ndarray, z_meas: np.ndarray, threshold_px: float,
                  ransac_iterations: int, min_inliers: int, depth_noise: float, huber: float,
                  prior: MotionPrior | None = None, initial: np.ndarray | None = None,
                  trust_initial: float = 0.8) -> tuple[np.ndarray | None, np.ndarray, str]:
    """RANSAC PnP, then robust refinement on the inliers, re-classification of every correspondence and a
    second refinement. Returns (T_cw or None, inlier mask, why it failed or "").

    With an ``initial`` pose (a good prediction), RANSAC is skipped when a robust refinement from it
    already explains at least ``trust_initial`` of the correspondences: the common case between
    keyframes, where the correspondences come from optical flow."""
    count = len(xy)
    if count < min_inliers:
        return None, np.zeros(count, bool), f"too few matches ({count} < {min_inliers})"
    if initial is not None:
        T_cw = refine_pose(K, initial, points_w, xy, z_meas, depth_noise, huber, prior=prior)
        inliers = inliers_of(K, T_cw, points_w, xy, z_meas, threshold_px, depth_noise)
        if inliers.sum() >= max(min_inliers, trust_initial * count):
            T_cw = refine_pose(K, T_cw, points_w[inliers], xy[inliers], z_meas[inliers], depth_noise, huber,
                               prior=prior)
            return T_cw, inliers_of(K, T_cw, points_w, xy, z_meas, threshold_px, depth_noise), ""
    T_cw, inliers = pnp_ransac(K, points_w, xy, threshold_px, ransac_iterations)
    if T_cw is None or inliers.sum() < min_inliers:
        return None, inliers, f"RANSAC found too few inliers ({int(inliers.sum())} of {count} matches)"
    for _ in range(2):
        T_cw = refine_pose(K, T_cw, points_w[inliers], xy[inliers], z_meas[inliers], depth_noise, huber, prior=prior)
        inliers = inliers_of(K, T_cw, points_w, xy, z_meas, threshold_px, depth_noise)
        if inliers.sum() < min_inliers:
            return None, inliers, f"too few inliers after refinement ({int(inliers.sum())} < {min_inliers})"
    return T_cw, inliers, ""


@dataclass
class PoseEstimate:
    """The outcome of one attempt to estimate a frame's pose against the map (tracking, relocalisation, a
    keyframe's description)."""

    ok: bool
    reason: str
    T_cw: np.ndarray | None = None
    num_matches: int = 0
    num_inliers: int = 0
    keypoint_landmarks: np.ndarray | None = None  # (N,) landmark id per keypoint, -1 = none
    suspect: np.ndarray | None = None  # (N,) keypoints matched but rejected: not used for new landmarks
    prior: MotionPrior | None = None  # the motion-model prior the pose was refined with
