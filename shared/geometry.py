"""Rigid-body geometry: quaternions, SE(3) matrices, batched SO(3) helpers, Umeyama alignment and the Huber loss.

Conventions: poses are 4x4 camera-to-world matrices; quaternions are (qx, qy, qz, qw)
as in the TUM format (scipy's default order). Quaternions, rotation vectors and their matrices are
converted by ``scipy.spatial.transform.Rotation``, vectorised.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) in (x, y, z, w) order; normalises first.

    A zero or non-finite quaternion gives a NaN matrix (scipy would raise)."""
    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4)
    ok = np.isfinite(flat).all(axis=1) & (np.linalg.norm(flat, axis=1) > 0)
    if ok.all():
        return Rotation.from_quat(flat).as_matrix().reshape(q.shape[:-1] + (3, 3))
    out = np.full((len(flat), 3, 3), np.nan)
    out[ok] = Rotation.from_quat(flat[ok]).as_matrix()
    return out.reshape(q.shape[:-1] + (3, 3))


def rot_to_quat(r: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) in (x, y, z, w) order with w >= 0 from rotation matrices (..., 3, 3).

    A non-finite matrix gives a NaN quaternion; a matrix that is no rotation (det <= 0) raises ValueError."""
    r = np.asarray(r, dtype=np.float64)
    flat = r.reshape(-1, 3, 3)
    ok = np.isfinite(flat).all(axis=(1, 2))
    if ok.all():
        return Rotation.from_matrix(flat).as_quat(canonical=True).reshape(r.shape[:-2] + (4,))
    out = np.full((len(flat), 4), np.nan)
    out[ok] = Rotation.from_matrix(flat[ok]).as_quat(canonical=True)
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
    """Rotation matrices (..., 3, 3) from axis-angle vectors (..., 3) (scipy's Rodrigues, stable near zero)."""
    return Rotation.from_rotvec(np.asarray(omega, dtype=np.float64)).as_matrix()


def so3_log(r: np.ndarray) -> np.ndarray:
    """Axis-angle vectors (..., 3), angle in [0, pi], of rotation matrices (..., 3, 3) (inverse of Rodrigues)."""
    return Rotation.from_matrix(np.asarray(r, dtype=np.float64)).as_rotvec()


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
    """Rotation matrix from one axis-angle 3-vector (Rodrigues); :func:`so3_exp_batch` for many."""
    omega = np.asarray(omega, dtype=np.float64)
    if omega.shape != (3,):
        raise ValueError(f"so3_exp takes one 3-vector, got shape {omega.shape}; so3_exp_batch takes many")
    return so3_exp_batch(omega)


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
