"""Rigid-body geometry: quaternions, SE(3) matrices, batched SO(3) helpers, Umeyama alignment and the Huber loss.

Conventions: poses are 4x4 camera-to-world matrices; quaternions are (qx, qy, qz, qw)
as in the TUM format.
"""

from __future__ import annotations

import cv2
import numpy as np


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from quaternions (..., 4) in (x, y, z, w) order; normalises first."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - z * w)
    r[..., 0, 2] = 2 * (x * z + y * w)
    r[..., 1, 0] = 2 * (x * y + z * w)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - x * w)
    r[..., 2, 0] = 2 * (x * z - y * w)
    r[..., 2, 1] = 2 * (y * z + x * w)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def rot_to_quat(r: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) with w >= 0 from rotation matrices (..., 3, 3)."""
    r = np.asarray(r, dtype=np.float64)
    flat = r.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        t = np.trace(m)
        if t > 0:
            s = 2.0 * np.sqrt(t + 1.0)
            out[i] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            out[i] = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            out[i] = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            out[i] = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[out[:, 3] < 0] *= -1
    return out.reshape(r.shape[:-2] + (4,))


def make_pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """A 4x4 homogeneous transform from a 3x3 rotation and a 3-vector."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = np.asarray(translation).reshape(3)
    return pose


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of one or many rigid transforms (..., 4, 4), using R^T instead of a general inverse."""
    pose = np.asarray(pose, dtype=np.float64)
    inv = np.zeros_like(pose)
    rt = np.swapaxes(pose[..., :3, :3], -1, -2)
    inv[..., :3, :3] = rt
    inv[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, pose[..., :3, 3])
    inv[..., 3, 3] = 1.0
    return inv


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of rotation matrices (..., 3, 3)."""
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): ``skew(v) @ x == np.cross(v, x)``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp_batch(omega: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from axis-angle vectors (..., 3) (Rodrigues, stable near zero).

    Not bit-identical to :func:`so3_exp` (other operation order and small-angle branch)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    k = skew(omega)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def so3_log(r: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) of one rotation matrix (inverse of Rodrigues)."""
    rvec, _ = cv2.Rodrigues(np.asarray(r, dtype=np.float64))
    return rvec.reshape(3)


def huber_weights(res: np.ndarray, threshold: float) -> np.ndarray:
    """IRLS weights of the Huber loss, element by element: 1 within ``threshold``, ``threshold / |r|`` beyond."""
    abs_r = np.abs(res)
    return np.where(abs_r <= threshold, 1.0, threshold / np.maximum(abs_r, 1e-12))


def huber_loss(res: np.ndarray, threshold: float) -> np.ndarray:
    """Huber loss element by element: ``r**2 / 2`` within ``threshold``, ``threshold * (|r| - threshold / 2)`` beyond
    (continuous, with the gradient ``huber_weights(r) * r``)."""
    abs_r = np.abs(res)
    return np.where(abs_r <= threshold, 0.5 * abs_r**2, threshold * (abs_r - 0.5 * threshold))


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix from an axis-angle 3-vector (Rodrigues)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega)
    k = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    if theta < 1e-12:
        return np.eye(3) + k
    k /= theta
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * (k @ k)


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation closest to a 3x3 matrix in the Frobenius sense (removes scale and shear)."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (R, t, s) with target ~ s * R @ source + t (Umeyama, PAMI 1991).

    ``source`` and ``target`` are (N, 3) arrays of corresponding points.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(f"umeyama needs two (N, 3) arrays of equal shape, got {source.shape} and {target.shape}")
    if len(source) < 3:
        raise ValueError("umeyama needs at least 3 point pairs")
    mean_s = source.mean(axis=0)
    mean_t = target.mean(axis=0)
    xs = source - mean_s
    xt = target - mean_t
    var_s = (xs**2).sum() / len(source)
    cov = xt.T @ xs / len(source)
    u, d, vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise ValueError("degenerate point set: Umeyama alignment is not possible")
    s_mat = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_mat[2, 2] = -1
    rotation = u @ s_mat @ vt
    scale = float(np.trace(np.diag(d) @ s_mat) / var_s) if with_scale else 1.0
    translation = mean_t - scale * rotation @ mean_s
    return rotation, translation, scale


def backproject(xy: np.ndarray, depth: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Camera-frame 3-D points (N, 3) of pixels ``xy`` (N, 2) at depths ``depth`` (N,) along the optical axis.

    ``k`` is the 3x3 pinhole matrix; pixel coordinates follow the pixel-centre convention of ``k``.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    if len(depth) != len(xy):
        raise ValueError(f"backproject needs one depth per pixel, got {len(xy)} pixels and {len(depth)} depths")
    x = (xy[:, 0] - k[0, 2]) / k[0, 0] * depth
    y = (xy[:, 1] - k[1, 2]) / k[1, 1] * depth
    return np.stack([x, y, depth], axis=1)


def project(points: np.ndarray, k: np.ndarray, min_depth: float = 1e-6) -> np.ndarray:
    """Pixels (N, 2) of camera-frame points (N, 3); points not in front of the camera (z <= min_depth) get NaN."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    z = points[:, 2]
    in_front = z > min_depth
    safe_z = np.where(in_front, z, 1.0)
    u = np.where(in_front, k[0, 0] * points[:, 0] / safe_z + k[0, 2], np.nan)
    v = np.where(in_front, k[1, 1] * points[:, 1] / safe_z + k[1, 2], np.nan)
    return np.stack([u, v], axis=1)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) moved by a 4x4 rigid transform: ``R @ p + t`` for each row."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return points @ pose[:3, :3].T + pose[:3, 3]


def depth_at_pixels(depth: np.ndarray, xy: np.ndarray, min_depth: float = 0.1, max_depth: float = 8.0) -> np.ndarray:
    """Depth (N,) at the nearest pixel of each point; NaN outside the image or outside [min_depth, max_depth].

    Nearest, not bilinear: interpolating across a depth edge invents a surface between a person and the wall."""
    depth = np.asarray(depth)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    height, width = depth.shape
    out = np.full(len(xy), np.nan)
    with np.errstate(invalid="ignore"):
        col = np.round(xy[:, 0])
        row = np.round(xy[:, 1])
        inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    values = depth[row[inside].astype(np.int64), col[inside].astype(np.int64)].astype(np.float64)
    with np.errstate(invalid="ignore"):
        out[inside] = np.where((values >= min_depth) & (values <= max_depth), values, np.nan)
    return out
