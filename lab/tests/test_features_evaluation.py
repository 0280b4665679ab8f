"""Reprojection, repeatability and match correctness, on synthetic sequences where the answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.config import DetectorConfig
from twohr.dataset import RGBDSequence
from twohr.features import mutual_nn
from twohr.geometry import backproject, depth_at_pixels, invert_pose, make_pose, project, so3_exp, transform_points
from twohr.trajectory import interpolate_poses
from twohr_lab.features.evaluation import clustered_fraction, match_precision, repeatability
from twohr_lab.pairs import correct_matches, relative_pose, reproject, shared_view
from twohr_services.detector.core import R2D2Detector

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


def test_backproject_project_round_trip():
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, 0], [640, 480], (100, 2))
    depth = rng.uniform(0.5, 6, 100)
    points = backproject(xy, depth, K)
    assert np.allclose(points[:, 2], depth)
    assert np.allclose(project(points, K), xy)
    behind = project(np.array([[0.1, 0.2, -1.0], [0.0, 0.0, 0.0]]), K)
    assert np.isnan(behind).all()
    pose = make_pose(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([0.5, 0.1, -0.2]))
    assert np.allclose(transform_points(invert_pose(pose), transform_points(pose, points)), points)


def test_reproject_known_translation():
    depth = np.full((480, 640), 2.0, np.float32)
    depth[:10] = 0  # no reading in the top rows
    xy_a = np.array([[319.5, 239.5], [100.0, 300.0], [50.0, 5.0]])
    t_b_a = make_pose(np.eye(3), np.array([-0.1, 0.0, 0.0]))  # camera B is 10 cm to the right of A
    xy_b, valid = reproject(xy_a, depth, K, t_b_a)
    assert valid.tolist() == [True, True, False]
    # a point at 2 m moves by f * 0.1 / 2 = 25 px to the left
    assert np.allclose(xy_b[:2], xy_a[:2] - [25, 0])
    assert np.isnan(xy_b[2]).all()


def test_sample_depth_is_nearest_and_rejects_missing():
    depth = np.zeros((4, 4), np.float32)
    depth[1, 2] = 3.0
    values = depth_at_pixels(depth, np.array([[2.2, 0.8], [0.0, 0.0], [9.0, 1.0], [np.nan, 1.0]]))
    assert values[0] == 3.0
    assert np.isnan(values[1:]).all()


@pytest.fixture(scope="module")
def synthetic(synthetic_sequence):
    sequence = RGBDSequence(synthetic_sequence)
    gt = sequence.ground_truth()
    poses, valid = interpolate_poses(gt, sequence.stamps)
    return sequence, poses, valid


def test_poses_at_reproduces_and_interpolates_the_trajectory(synthetic):
    sequence, poses, valid = synthetic
    gt = sequence.ground_truth()
    inner = valid.copy()
    assert inner[1:-1].all()
    assert np.allclose(poses[inner], gt.poses[inner], atol=1e-9)
    middle, ok = interpolate_poses(gt, (gt.stamps[10:11] + gt.stamps[11:12]) / 2)
    assert ok.all()
    assert np.allclose(middle[0, :3, 3], (gt.poses[10, :3, 3] + gt.poses[11, :3, 3]) / 2)
    outside, ok = interpolate_poses(gt, gt.stamps[:1] - 1.0)
    assert not ok.any()


def test_exact_reprojection_is_fully_repeatable(synthetic):
    """A keypoint set moved into B by ground truth is repeated 100 %; shifted by 4 px it is not at 3 px."""
    sequence, poses, _ = synthetic
    a, b = 20, 25
    frame_a, frame_b = sequence.read(a), sequence.read(b)
    t_b_a = relative_pose(poses[a], poses[b])
    grid = np.mgrid[8:232:16, 8:312:16].reshape(2, -1).T[:, ::-1]  # sparse, so a 4 px shift finds no neighbour
    xy_a = grid + np.random.default_rng(1).uniform(-2, 2, grid.shape)
    xy_b, visible = shared_view(xy_a, frame_a.depth, sequence.camera.matrix, t_b_a, (320, 240), frame_b.depth)
    assert visible.sum() > 0.6 * len(xy_a)
    result = repeatability(xy_a, xy_b[visible], frame_a.depth, sequence.camera.matrix, t_b_a, (320, 240),
                           frame_b.depth)
    assert result.shared == visible.sum()
    assert result.ratio == 1.0 and result.ratio_one_to_one == 1.0
    shifted = repeatability(xy_a, xy_b[visible] + [4.0, 0.0], frame_a.depth, sequence.camera.matrix, t_b_a,
                            (320, 240), frame_b.depth)
    assert shifted.repeated == 0


def test_depth_check_removes_the_moving_box(synthetic, synthetic_sequence):
    """Points on the walking box do not reproject onto consistent depth in B: outside the shared view."""
    import cv2

    sequence, poses, _ = synthetic
    masks = sorted((synthetic_sequence / "dynamic").glob("*.png"))
    a = next(i for i in range(0, 50) if (cv2.imread(str(masks[i]), 0) > 0).sum() > 2000)
    b = a + 8
    frame_a, frame_b = sequence.read(a), sequence.read(b)
    dynamic = cv2.imread(str(masks[a]), 0) > 0
    ys, xs = np.nonzero(dynamic)
    xy_a = np.stack([xs, ys], axis=1)[:: max(1, len(xs) // 300)].astype(float)
    t_b_a = relative_pose(poses[a], poses[b])
    _, with_depth_check = shared_view(xy_a, frame_a.depth, sequence.camera.matrix, t_b_a, (320, 240), frame_b.depth)
    _, geometric_only = shared_view(xy_a, frame_a.depth, sequence.camera.matrix, t_b_a, (320, 240))
    assert geometric_only.mean() > 0.9
    assert with_depth_check.mean() < 0.5


def test_correct_matches_by_reprojection(synthetic):
    sequence, poses, _ = synthetic
    a, b = 5, 6
    frame_a, frame_b = sequence.read(a), sequence.read(b)
    k = sequence.camera.matrix
    t_b_a = relative_pose(poses[a], poses[b])
    xy_a = np.random.default_rng(2).uniform([20, 20], [300, 220], (50, 2))
    xy_b, valid = reproject(xy_a, frame_a.depth, k, t_b_a)
    assert valid.all()
    idx = np.arange(50)
    correct, verifiable = correct_matches(xy_a, xy_b, idx, idx, frame_a.depth, frame_b.depth, k, t_b_a)
    assert correct.all() and verifiable.all()
    wrong, _ = correct_matches(xy_a, xy_b, idx, np.roll(idx, 1), frame_a.depth, frame_b.depth, k, t_b_a)
    assert wrong.mean() < 0.1
    # without depth in A the check falls back to B -> A; without depth in either it is not verifiable
    no_depth = np.zeros_like(frame_a.depth)
    correct_ba, verifiable_ba = correct_matches(xy_a, xy_b, idx, idx, no_depth, frame_b.depth, k, t_b_a)
    assert verifiable_ba.all() and correct_ba.mean() > 0.95
    _, none = correct_matches(xy_a, xy_b, idx, idx, no_depth, no_depth, k, t_b_a)
    assert not none.any()


def test_clustered_fraction():
    spread = np.mgrid[0:100:10, 0:100:10].reshape(2, -1).T.astype(float)
    assert clustered_fraction(spread, 3.0) == 0.0
    stacked = np.concatenate([spread, spread[:25] + 0.5])  # 25 points re-detected half a pixel away
    assert clustered_fraction(stacked, 3.0) == pytest.approx(50 / 125)
    assert clustered_fraction(spread[:1]) == 0.0


def test_mutual_nearest_neighbours():
    rng = np.random.default_rng(4)
    desc = rng.normal(size=(30, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    perm = rng.permutation(30)
    matches = mutual_nn(desc, desc[perm] + 0.01)
    assert len(matches) == 30 and np.array_equal(perm[matches.idx_b], matches.idx_a)
    bits = rng.integers(0, 256, (20, 32), dtype=np.uint8)
    matches = mutual_nn(bits, bits[::-1])
    assert np.array_equal(matches.idx_b, 19 - matches.idx_a) and len(matches) == 20
    assert len(mutual_nn(desc[:0], desc)) == 0


def test_real_2hr_detections_on_a_static_synthetic_pair(static_synthetic_sequence):
    """The real detector on rendered frames of a static room: high repeatability and precision."""
    sequence = RGBDSequence(static_synthetic_sequence)
    poses, _ = interpolate_poses(sequence.ground_truth(), sequence.stamps)
    detector = R2D2Detector(DetectorConfig(latency_budget_ms=None))
    a, b = 10, 12
    frame_a, frame_b = sequence.read(a), sequence.read(b)
    kp_a, kp_b = detector.detect(frame_a.rgb), detector.detect(frame_b.rgb)
    k = sequence.camera.matrix
    t_b_a = relative_pose(poses[a], poses[b])
    rep = repeatability(kp_a.xy, kp_b.xy, frame_a.depth, k, t_b_a, (320, 240), frame_b.depth)
    prec = match_precision(kp_a.xy, kp_a.descriptors, kp_b.xy, kp_b.descriptors, frame_a.depth, frame_b.depth,
                           k, t_b_a)
    assert len(kp_a) > 100 and rep.shared > 0.8 * len(kp_a)
    assert rep.ratio > 0.7
    assert prec.matches > 50 and prec.ratio > 0.8
    # the same keypoints against a wrong pose are not repeatable: the metric can fail
    wrong_pose = make_pose(so3_exp(np.array([0.0, 0.05, 0.0])), np.zeros(3)) @ t_b_a
    assert repeatability(kp_a.xy, kp_b.xy, frame_a.depth, k, wrong_pose, (320, 240)).ratio < 0.4
