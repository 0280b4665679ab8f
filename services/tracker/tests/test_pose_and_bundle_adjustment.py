"""The tracker's geometry and least squares on small synthetic problems: depth sampling, PnP, pose refinement
and local bundle adjustment."""

from __future__ import annotations

import numpy as np

from twohr.geometry import invert_pose, project, so3_exp_batch, so3_log, transform_points
from twohr.pose import MotionPrior, pnp_ransac, pose_difference, refine_pose, sample_depth
from twohr_services.tracker.bundle_adjustment import bundle_adjust

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


def random_pose(rng: np.random.Generator, rotation: float, translation: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = so3_exp_batch(rng.normal(0, rotation, 3))
    pose[:3, 3] = rng.normal(0, translation, 3)
    return pose


def scene_points(rng: np.random.Generator, count: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-2, 2, count), rng.uniform(-1.5, 1.5, count), rng.uniform(2, 5, count)])


def test_so3_log_inverts_exp():
    rng = np.random.default_rng(0)
    for omega in rng.normal(0, 0.8, (20, 3)):
        assert np.allclose(so3_log(so3_exp_batch(omega)), omega, atol=1e-9)


def test_sample_depth_rejects_edges_holes_and_range():
    depth = np.full((40, 40), 2.0)
    depth[:, 20:] = 3.0  # a depth edge at x = 19.5
    depth[5, 5] = 0.0  # a hole
    depth[30:, :10] = 9.0  # beyond max_depth
    xy = np.array([[10.0, 10], [19.0, 10], [25.0, 10], [5.0, 5], [5.0, 35], [6.0, 6]])
    z = sample_depth(depth, xy, min_depth=0.1, max_depth=6.0, edge_ratio=0.05)
    assert z.tolist() == [2.0, 0.0, 3.0, 0.0, 0.0, 2.0]


def test_pnp_ransac_and_refinement_recover_the_pose_despite_outliers():
    rng = np.random.default_rng(1)
    points = scene_points(rng, 300)
    truth = random_pose(rng, 0.05, 0.1)
    camera_points = transform_points(truth, points)
    xy = project(camera_points, K) + rng.normal(0, 0.3, (300, 2))
    xy[:90] = rng.uniform([0, 0], [640, 480], (90, 2))  # 30 % gross outliers
    T_cw, inliers = pnp_ransac(K, points, xy, threshold_px=2.0, iterations=200)
    assert T_cw is not None
    assert inliers[90:].mean() > 0.95 and inliers[:90].mean() < 0.1
    refined = refine_pose(K, T_cw, points[inliers], xy[inliers], camera_points[inliers, 2], depth_noise=0.002,
                          huber=2.0)
    moved, turned = pose_difference(invert_pose(truth), invert_pose(refined))
    assert moved < 0.003 and turned < 0.05


def test_motion_prior_holds_a_pose_without_observations():
    prior_pose = random_pose(np.random.default_rng(2), 0.1, 0.2)
    empty = np.zeros((0, 3))
    refined = refine_pose(K, np.eye(4), empty, np.zeros((0, 2)), np.zeros(0), 0.005, 2.0,
                          prior=MotionPrior(prior_pose, 0.02, np.radians(2)))
    assert np.allclose(refined, prior_pose, atol=1e-6)


def make_ba_problem(seed: int = 3, poses: int = 5, points: int = 800, outliers: int = 40):
    """Noisy observations of a static scene from a short camera path; returns truth and perturbed start."""
    rng = np.random.default_rng(seed)
    world = scene_points(rng, points)
    truth_cw = []
    for k in range(poses):
        pose_wc = random_pose(rng, 0.03, 0.01)
        pose_wc[:3, 3] += [0.08 * k, 0.02 * k, 0.0]
        truth_cw.append(invert_pose(pose_wc))
    truth_cw = np.array(truth_cw)
    obs_pose, obs_point, obs_xy, obs_depth = [], [], [], []
    for k in range(poses):
        camera_points = transform_points(truth_cw[k], world)
        uv = project(camera_points, K)
        seen = np.flatnonzero((uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
                              & (rng.random(points) < 0.8))
        obs_pose.append(np.full(len(seen), k))
        obs_point.append(seen)
        obs_xy.append(uv[seen] + rng.normal(0, 0.5, (len(seen), 2)))
        obs_depth.append(camera_points[seen, 2] * (1 + rng.normal(0, 0.002, len(seen))))
    obs_pose, obs_point, obs_xy, obs_depth = map(np.concatenate, (obs_pose, obs_point, obs_xy, obs_depth))
    bad = rng.choice(len(obs_xy), outliers, replace=False)
    obs_xy[bad] += rng.choice([-1, 1], (outliers, 2)) * rng.uniform(20, 60, (outliers, 2))
    start_cw = truth_cw.copy()
    for k in range(1, poses):
        start_cw[k] = random_pose(rng, 0.01, 0.02) @ truth_cw[k]
    start_points = world + rng.normal(0, 0.03, world.shape)
    return truth_cw, world, start_cw, start_points, obs_pose, obs_point, obs_xy, obs_depth, bad


def test_bundle_adjustment_reduces_reprojection_error_and_flags_outliers():
    truth_cw, world, start_cw, start_points, obs_pose, obs_point, obs_xy, obs_depth, bad = make_ba_problem()
    fixed = np.zeros(len(start_cw), bool)
    fixed[0] = True
    result = bundle_adjust(K, start_cw, start_points, obs_pose, obs_point, obs_xy, obs_depth, fixed,
                           depth_noise=0.002, huber=2.0, max_iterations=10)
    assert result.final_rms_px < 0.25 * result.initial_rms_px
    assert result.final_rms_px < 1.0  # the observation noise is 0.5 px per axis
    assert np.array_equal(result.poses_cw[0], start_cw[0])  # the gauge stays put
    def error(a, b):
        return pose_difference(invert_pose(a), invert_pose(b))[0]

    before = [error(t, s) for t, s in zip(truth_cw[1:], start_cw[1:], strict=True)]
    after = [error(t, r) for t, r in zip(truth_cw[1:], result.poses_cw[1:], strict=True)]
    assert min(before) > 0.01 and max(after) < 0.003
    assert np.median(np.linalg.norm(result.points_w - world, axis=1)) < 0.01
    flagged = np.flatnonzero(result.outliers)
    assert np.isin(bad, flagged).mean() > 0.9 and len(flagged) < 2 * len(bad)
