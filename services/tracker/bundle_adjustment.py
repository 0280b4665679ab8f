"""Bundle adjustment: Levenberg-Marquardt with Huber weights over keyframe poses and landmarks, the points
eliminated by the Schur complement (block normal equations, shared with the lab's consistency check). Pure
functions on numpy arrays; the residuals are :mod:`twohr.pose`'s."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twohr.geometry import huber_loss, huber_weights
from twohr.pose import apply_update, observation_residuals, pose_jacobian


@dataclass
class BundleAdjustmentResult:
    """Refined poses and points, and the RMS reprojection error (px) of the inlier observations before/after."""

    poses_cw: np.ndarray
    points_w: np.ndarray
    initial_rms_px: float
    final_rms_px: float
    outliers: np.ndarray
    iterations: int


def _sum_by(index: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """Sum rows of ``values`` (N, ...) into ``count`` bins given by ``index`` (N,)."""
    flat = values.reshape(len(values), -1)
    # one bincount per column: much faster than np.add.at
    out = np.stack([np.bincount(index, weights=flat[:, j], minlength=count) for j in range(flat.shape[1])], axis=1)
    return out.reshape((count,) + values.shape[1:])


def _same_point_pairs(obs_point: np.ndarray, members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All ordered pairs (a, b) of observations in ``members`` that see the same point (a == b included)."""
    members = members[np.argsort(obs_point[members], kind="stable")]
    points, starts, counts = np.unique(obs_point[members], return_index=True, return_counts=True)
    group = np.repeat(np.arange(len(points)), counts)
    reps = counts[group]
    first = np.repeat(np.arange(len(members)), reps)
    offset = np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps)
    second = np.repeat(starts[group], reps) + offset
    return members[first], members[second]


@dataclass
class SchurLayout:
    """Who touches what in a least-squares problem where each observation touches one pose and one point.

    ``obs_slot[o]`` is the free-pose slot of observation ``o`` (-1: its pose is fixed) and ``obs_point[o]`` its
    point; ``pair_a``/``pair_b`` are all ordered pairs of observations from free poses that see the same point
    (they fill the reduced pose system)."""

    obs_slot: np.ndarray
    obs_point: np.ndarray
    n_free: int
    n_points: int
    free_obs: np.ndarray
    pair_a: np.ndarray
    pair_b: np.ndarray


def schur_layout(obs_slot: np.ndarray, obs_point: np.ndarray, n_free: int, n_points: int) -> SchurLayout:
    """The :class:`SchurLayout` of observations with free-pose slots ``obs_slot`` (-1 = fixed pose) and points
    ``obs_point``; computed once per problem, reused by every iteration."""
    obs_slot = np.asarray(obs_slot, np.int64)
    obs_point = np.asarray(obs_point, np.int64)
    free_obs = np.flatnonzero(obs_slot >= 0)
    pair_a, pair_b = _same_point_pairs(obs_point, free_obs)
    return SchurLayout(obs_slot, obs_point, int(n_free), int(n_points), free_obs, pair_a, pair_b)


@dataclass
class NormalEquations:
    """Gauss-Newton normal equations ``J^T W J step = -J^T W r`` in blocks: ``h_pose`` (F, d, d) and ``g_pose``
    (F, d) per free pose, ``h_point`` (M, 3, 3) and ``g_point`` (M, 3) per point (from every observation, fixed
    poses' included) and the pose-point coupling ``h_cross`` (O, d, 3) per observation (used for free poses')."""

    layout: SchurLayout
    h_pose: np.ndarray
    g_pose: np.ndarray
    h_point: np.ndarray
    g_point: np.ndarray
    h_cross: np.ndarray


def normal_equations(layout: SchurLayout, jac_pose: np.ndarray, jac_point: np.ndarray, res: np.ndarray,
                     weights: np.ndarray) -> NormalEquations:
    """The block normal equations of residuals ``res`` (O, R) with IRLS ``weights`` (O, R) and Jacobians
    ``jac_pose`` (O, R, d) with respect to the observing pose's update and ``jac_point`` (O, R, 3) with respect to
    the point."""
    free_obs, obs_slot, obs_point = layout.free_obs, layout.obs_slot, layout.obs_point
    w_jac_pose = jac_pose * weights[:, :, None]
    w_jac_point = jac_point * weights[:, :, None]
    w_jac_pose_t = np.swapaxes(w_jac_pose, 1, 2)
    h_pose = _sum_by(obs_slot[free_obs], w_jac_pose_t[free_obs] @ jac_pose[free_obs], layout.n_free)
    g_pose = _sum_by(obs_slot[free_obs], (w_jac_pose_t[free_obs] @ res[free_obs, :, None])[:, :, 0], layout.n_free)
    w_jac_point_t = np.swapaxes(w_jac_point, 1, 2)
    h_point = _sum_by(obs_point, w_jac_point_t @ jac_point, layout.n_points)
    g_point = _sum_by(obs_point, (w_jac_point_t @ res[:, :, None])[:, :, 0], layout.n_points)
    h_cross = w_jac_pose_t @ jac_point  # (O, d, 3), used for free observations
    return NormalEquations(layout, h_pose, g_pose, h_point, g_point, h_cross)


def solve_schur(normal: NormalEquations, damping: float) -> tuple[np.ndarray, np.ndarray] | None:
    """One Levenberg-Marquardt step ``(step_pose (F, d), step_point (M, 3))`` of block normal equations.

    The diagonals are scaled by ``1 + damping`` (plus 1e-9 for rank-deficient blocks); the points are eliminated
    per 3x3 block (Schur complement), the dense (d F x d F) reduced pose system is solved and the point steps are
    substituted back. ``None`` when the reduced system is singular (retry with more damping)."""
    lay = normal.layout
    h_pose, h_point, h_cross, g_point = normal.h_pose, normal.h_point, normal.h_cross, normal.g_point
    n_free, dim = lay.n_free, h_pose.shape[1]
    free_obs, obs_slot, obs_point, pair_a, pair_b = lay.free_obs, lay.obs_slot, lay.obs_point, lay.pair_a, lay.pair_b
    hp = h_pose + damping * np.einsum("pii->pi", h_pose)[:, :, None] * np.eye(dim) + 1e-9 * np.eye(dim)
    hl = h_point + damping * np.einsum("mii->mi", h_point)[:, :, None] * np.eye(3) + 1e-9 * np.eye(3)
    hl_inv = np.linalg.inv(hl)
    reduced = h_cross[pair_a] @ hl_inv[obs_point[pair_a]] @ np.swapaxes(h_cross[pair_b], 1, 2)
    schur = -_sum_by(obs_slot[pair_a] * n_free + obs_slot[pair_b], reduced, n_free * n_free).reshape(
        n_free, n_free, dim, dim)
    schur[np.arange(n_free), np.arange(n_free)] += hp
    rhs = -normal.g_pose + _sum_by(obs_slot[free_obs], (h_cross[free_obs] @ hl_inv[obs_point[free_obs]] @ g_point[
        obs_point[free_obs], :, None])[:, :, 0], n_free)
    system = schur.transpose(0, 2, 1, 3).reshape(dim * n_free, dim * n_free)
    try:
        step_pose = np.linalg.solve(system, rhs.reshape(-1)).reshape(n_free, dim) if n_free else np.zeros((0, dim))
    except np.linalg.LinAlgError:
        return None
    coupling = _sum_by(obs_point[free_obs], (np.swapaxes(h_cross[free_obs], 1, 2) @ step_pose[
        obs_slot[free_obs], :, None])[:, :, 0], lay.n_points)
    step_point = (hl_inv @ (-g_point - coupling)[:, :, None])[:, :, 0]
    return step_pose, step_point


def bundle_adjust(K: np.ndarray, poses_cw: np.ndarray, points_w: np.ndarray, obs_pose: np.ndarray,
                  obs_point: np.ndarray, obs_xy: np.ndarray, obs_depth: np.ndarray, fixed: np.ndarray,
                  depth_noise: float, huber: float, max_iterations: int = 10,
                  outlier_threshold: float = 4.0) -> BundleAdjustmentResult:
    """Local bundle adjustment: Levenberg-Marquardt with Huber weights (IRLS) and the Schur complement.

    ``poses_cw`` (P, 4, 4) world-to-camera; ``points_w`` (M, 3); observation ``o`` sees point
    ``obs_point[o]`` from pose ``obs_pose[o]`` at pixel ``obs_xy[o]`` with depth ``obs_depth[o]`` (0 = none).
    Poses with ``fixed`` set stay put (they fix the gauge). Each observation touches one pose and one
    point, so the pose block and the point block of the normal equations are block-diagonal: the
    points are eliminated per 3x3 block and only a small dense (6 x free poses) system is solved
    (:func:`normal_equations`, :func:`solve_schur`).
    ``outliers`` flags observations whose reprojection or depth residual exceeds ``outlier_threshold``
    after the adjustment.
    """
    poses = np.asarray(poses_cw, dtype=np.float64).copy()
    points = np.asarray(points_w, dtype=np.float64).copy()
    obs_pose = np.asarray(obs_pose, np.int64)
    obs_point = np.asarray(obs_point, np.int64)
    n_points = len(points)
    free = ~np.asarray(fixed, bool)
    slot = np.full(len(poses), -1)
    slot[free] = np.arange(free.sum())
    n_free = int(free.sum())
    layout = schur_layout(slot[obs_pose], obs_point, n_free, n_points)

    def evaluate(poses: np.ndarray, points: np.ndarray):
        rot = poses[obs_pose, :3, :3]
        pc = (rot @ points[obs_point][:, :, None])[:, :, 0] + poses[obs_pose, :3, 3]
        res, jac_pc = observation_residuals(K, pc, obs_xy, obs_depth, depth_noise)
        return pc, rot, res, jac_pc

    def reprojection_rms(res: np.ndarray, mask: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum(res[mask, :2] ** 2, 1)))) if mask.any() else 0.0

    pc, rot, res, jac_pc = evaluate(poses, points)
    inliers0 = (np.hypot(res[:, 0], res[:, 1]) < outlier_threshold) & (np.abs(res[:, 2]) < outlier_threshold)
    initial_rms = reprojection_rms(res, inliers0)
    cost = float(huber_loss(res, huber).sum())
    damping = 1e-4
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        jac_pose = pose_jacobian(K, pc, obs_depth > 0, depth_noise)
        normal = normal_equations(layout, jac_pose, jac_pc @ rot, res, huber_weights(res, huber))
        improved = False
        for _attempt in range(6):
            steps = solve_schur(normal, damping)
            if steps is None:
                damping *= 10
                continue
            step_pose, step_point = steps
            trial_poses = poses.copy()
            for p in np.flatnonzero(free):
                trial_poses[p] = apply_update(poses[p], step_pose[slot[p]])
            trial_points = points + step_point
            t_pc, t_rot, t_res, t_jac = evaluate(trial_poses, trial_points)
            trial_cost = float(huber_loss(t_res, huber).sum())
            if trial_cost < cost:
                converged = cost - trial_cost < 1e-6 * cost
                poses, points, pc, rot, res, jac_pc, cost = trial_poses, trial_points, t_pc, t_rot, t_res, t_jac, \
                    trial_cost
                damping = max(damping / 3, 1e-7)
                improved = True
                break
            damping *= 5
        if not improved or converged:
            break
    outliers = (np.hypot(res[:, 0], res[:, 1]) > outlier_threshold) | (np.abs(res[:, 2]) > outlier_threshold)
    return BundleAdjustmentResult(poses, points, initial_rms, reprojection_rms(res, inliers0), outliers, iterations)
