"""ATE/RPE: hand-computed cases, and agreement with evo on the real ground truth."""

import numpy as np
import pytest

from twohr.evaluation import associate, evaluate
from twohr.geometry import make_pose, so3_exp
from twohr.trajectory import Trajectory, read_tum, write_tum


def line_trajectory(n=10, offset=0.0):
    stamps = np.arange(n) * 0.1
    poses = np.array([make_pose(np.eye(3), [i * 0.1 + offset, 0, 0]) for i in range(n)])
    return Trajectory(stamps, poses)


def circle_trajectory(n=10):
    angles = 2 * np.pi * np.arange(n) / n
    poses = np.array([make_pose(np.eye(3), [np.cos(a), np.sin(a), 0.0]) for a in angles])
    return Trajectory(np.arange(n) * 0.1, poses)


def test_hand_computed_ate():
    gt = circle_trajectory()
    est = circle_trajectory()
    # lift every second pose 3 cm out of the plane. The lifted poses sit evenly around the circle,
    # so no rotation helps: SE(3) alignment shifts by the mean (1.5 cm) and every error is 1.5 cm.
    est.poses[::2, 2, 3] += 0.03
    report, _ = evaluate(gt, est, align="se3", max_dt=0.01)
    assert report.ate.rmse == pytest.approx(0.015, abs=1e-9)
    report, _ = evaluate(gt, est, align="none", max_dt=0.01)
    assert report.ate.rmse == pytest.approx(np.sqrt(0.5 * 0.03**2), abs=1e-12)
    assert report.matched == 10 and report.gt_coverage == 100.0


def test_alignment_removes_rigid_motion():
    gt = line_trajectory()
    gt.poses[:, 2, 3] = np.sin(np.arange(10))  # not collinear
    world = make_pose(so3_exp(np.array([0.3, -0.2, 1.0])), [5, 1, -2])
    est = gt.transformed(left=world)
    report, _ = evaluate(gt, est)
    assert report.ate.rmse < 1e-9
    assert report.rpe_frame.rmse < 1e-9


def test_jitter_is_zero_for_smooth_drift_and_sees_a_zig_zag():
    gt = line_trajectory()
    drifting = line_trajectory()
    drifting.poses[:, 1, 3] += 0.003 * np.arange(10)  # a drift linear in time: no jitter
    report, _ = evaluate(gt, drifting, align="none", max_dt=0.01)
    assert report.jitter.rmse < 1e-12 and report.jitter.count == 8 and report.ate.rmse > 0.01
    zigzag = line_trajectory()
    zigzag.poses[:, 1, 3] += 0.002 * (-1.0) ** np.arange(10)  # +-2 mm every other frame
    report, _ = evaluate(gt, zigzag, align="none", max_dt=0.01)
    assert report.jitter.rmse == pytest.approx(0.008, abs=1e-12)  # |e - 2e' + e''| = 4 * 2 mm


def test_sim3_scale_measures_short_translations():
    gt = line_trajectory()
    gt.poses[:, 2, 3] = np.sin(np.arange(10))
    short = line_trajectory()
    short.poses[:, :3, 3] = gt.positions / 1.13  # every translation 13 % short
    report, _ = evaluate(gt, short)
    assert report.scale == 1.0 and report.sim3_scale == pytest.approx(1.13, abs=1e-9)
    report, _ = evaluate(gt, gt)
    assert report.sim3_scale == pytest.approx(1.0, abs=1e-9)


def test_association_window():
    ia, ib = associate(np.array([0.0, 1.0, 2.0]), np.array([0.005, 1.03, 1.99]), 0.02)
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 2]


def test_rpe_one_frame_hand_computed():
    gt = line_trajectory()
    est = line_trajectory()
    est.poses[5:, 0, 3] += 0.02  # one jump of 2 cm between frames 4 and 5
    report, _ = evaluate(gt, est, align="none", max_dt=0.01)
    assert report.rpe_frame.max == pytest.approx(0.02, abs=1e-12)
    assert report.rpe_frame.count == 9
    assert report.rpe_frame.median == pytest.approx(0.0, abs=1e-12)


def test_ground_truth_against_itself_is_zero(dev_sequence):
    gt = read_tum(dev_sequence / "groundtruth.txt")
    report, _ = evaluate(gt, gt)
    assert report.ate.rmse < 1e-12 and report.matched == len(gt)


def _perturbed(gt: Trajectory, seed=0) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = gt.poses.copy()
    poses[:, :3, 3] += np.cumsum(rng.normal(0, 0.004, (len(gt), 3)), axis=0)
    poses[:, :3, :3] = np.array([so3_exp(rng.normal(0, 0.01, 3)) @ r for r in poses[:, :3, :3]])
    stamps = gt.stamps + rng.uniform(-0.012, 0.012, len(gt))  # exercise the 0.02 s association window
    keep = np.sort(rng.choice(len(gt), int(0.8 * len(gt)), replace=False))
    return Trajectory(stamps[keep], poses[keep])


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_agrees_with_evo_on_real_ground_truth(dev_sequence, tmp_path, align):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    gt = read_tum(dev_sequence / "groundtruth.txt")
    est = _perturbed(gt)
    write_tum(tmp_path / "est.txt", est)
    report, _ = evaluate(gt, read_tum(tmp_path / "est.txt"), align=align, max_dt=0.02)

    ref = file_interface.read_tum_trajectory_file(str(dev_sequence / "groundtruth.txt"))
    evo_est = file_interface.read_tum_trajectory_file(str(tmp_path / "est.txt"))
    ref, evo_est = sync.associate_trajectories(ref, evo_est, max_diff=0.02)
    evo_est.align(ref, correct_scale=align == "sim3")
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, evo_est))
    stats = ape.get_all_statistics()
    assert report.matched == ref.num_poses
    assert report.ate.rmse == pytest.approx(stats["rmse"], abs=1e-6)
    assert report.ate.mean == pytest.approx(stats["mean"], abs=1e-6)
    assert report.ate.max == pytest.approx(stats["max"], abs=1e-6)
    assert report.ate.std == pytest.approx(stats["std"], abs=1e-6)
    assert report.ate.rmse > 0.01  # the perturbation is real

    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
    rpe.process_data((ref, evo_est))
    assert report.rpe_frame.rmse == pytest.approx(rpe.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)
