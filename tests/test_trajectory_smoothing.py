"""The trajectory smoother: frame noise goes, motion and gaps stay."""

import numpy as np
import pytest

from twohr.geometry import make_pose, rotation_angle, so3_exp
from twohr.trajectory import Trajectory, smooth_trajectory


def _hand_held(seconds: float = 10.0, rate: float = 30.0) -> Trajectory:
    """A camera on a 0.5 m circle (0.3 m/s^2), swaying in yaw and pitch, at camera rate."""
    stamps = np.arange(int(seconds * rate)) / rate
    angle = 2 * np.pi * stamps / 8.0
    poses = [make_pose(so3_exp([0.2 * np.sin(a), 0.3 * np.cos(0.7 * a), 0.0]),
                       [0.5 * np.cos(a), 0.5 * np.sin(a), 0.1 * a]) for a in angle]
    return Trajectory(stamps, np.array(poses))


def _noisy(truth: Trajectory, metres: float, radians: float, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = truth.poses.copy()
    poses[:, :3, 3] += rng.normal(0, metres, (len(truth), 3))
    poses[:, :3, :3] = np.array([p[:3, :3] @ so3_exp(rng.normal(0, radians, 3)) for p in truth.poses])
    return Trajectory(truth.stamps, poses)


def _rotation_errors(a: Trajectory, b: Trajectory) -> np.ndarray:
    return rotation_angle(np.swapaxes(a.poses[:, :3, :3], 1, 2) @ b.poses[:, :3, :3])


def test_frame_noise_is_removed_and_the_motion_kept():
    truth = _hand_held()
    noisy = _noisy(truth, metres=0.005, radians=np.radians(0.3))
    smooth = smooth_trajectory(noisy, acceleration=1.0, angular_acceleration=5.0)
    before = np.sqrt(np.mean(np.sum((noisy.positions - truth.positions) ** 2, 1)))
    after = np.sqrt(np.mean(np.sum((smooth.positions - truth.positions) ** 2, 1)))
    assert before == pytest.approx(0.005 * np.sqrt(3), rel=0.1)
    assert after < 0.4 * before, (before, after)
    # rotation is smoothed more gently: it is held to at least 5 rad/s^2 of angular acceleration
    rotation_before = np.sqrt(np.mean(_rotation_errors(noisy, truth) ** 2))
    assert np.sqrt(np.mean(_rotation_errors(smooth, truth) ** 2)) < 0.75 * rotation_before
    rotations = smooth.poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", rotations, rotations), np.tile(np.eye(3), (len(smooth), 1, 1)),
                               atol=1e-9)
    assert np.linalg.det(rotations) == pytest.approx(np.ones(len(smooth)))
    np.testing.assert_array_equal(smooth.stamps, noisy.stamps)


def test_a_clean_trajectory_is_left_as_it_is():
    """The noise is estimated from the trajectory: one without frame noise is not bent by the smoother."""
    truth = _hand_held()
    smooth = smooth_trajectory(truth, acceleration=1.0, angular_acceleration=5.0)
    assert np.abs(smooth.positions - truth.positions).max() < 2e-4
    assert _rotation_errors(smooth, truth).max() < 1e-3


def test_a_camera_that_really_accelerates_is_followed():
    """A 1 s loop of 0.25 m radius (10-20 m/s^2, far beyond the 1 m/s^2 floor): the smoother measures that
    acceleration and keeps the path instead of cutting its corners."""
    stamps = np.arange(30) / 30.0
    phase = 2 * np.pi * stamps
    poses = np.tile(np.eye(4), (30, 1, 1))
    poses[:, :3, 3] = np.column_stack([0.25 * np.sin(phase), 0.125 * np.sin(2 * phase), 0.3 * np.sin(phase / 2)])
    noisy = _noisy(Trajectory(stamps, poses), metres=0.002, radians=0.0, seed=2)
    smooth = smooth_trajectory(noisy, acceleration=1.0, angular_acceleration=5.0)
    assert np.sqrt(np.mean(np.sum((smooth.positions - poses[:, :3, 3]) ** 2, 1))) < 0.004


def test_runs_apart_are_smoothed_apart():
    """A 2 s gap (frames dropped) with a 1 m move across it: neither side is pulled towards the other."""
    truth = _hand_held(seconds=4.0)
    half = len(truth) // 2
    stamps = truth.stamps.copy()
    stamps[half:] += 2.0
    poses = truth.poses.copy()
    poses[half:, 0, 3] += 1.0
    gapped = _noisy(Trajectory(stamps, poses), metres=0.003, radians=0.0, seed=1)
    smooth = smooth_trajectory(gapped, acceleration=1.0, angular_acceleration=5.0)
    assert np.abs(smooth.positions - poses[:, :3, 3]).max() < 0.01
