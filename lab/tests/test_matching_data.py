"""Ground-truth geometry and pair labels, on exact synthetic RGB-D frames (one moving box plays a person)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from twohr.dataset import RGBDSequence
from twohr.features import Keypoints
from twohr.geometry import depth_at_pixels, make_pose, rotation_angle, so3_exp
from twohr.trajectory import Trajectory, interpolate_poses
from twohr_lab.matching.data import (
    MOVED,
    OCCLUDED,
    POSITIVE,
    VISIBLE,
    CachedFrame,
    LabelConfig,
    SplitConfig,
    frame_pairs,
    keypoint_repeatability,
    label_pairs,
    pair_geometry,
    split_frames,
)

FRAME_A, FRAME_B = 10, 22


def unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.standard_normal((n, 128)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def load(seq: RGBDSequence, index: int, xy: np.ndarray, desc: np.ndarray) -> tuple[CachedFrame, np.ndarray]:
    gt = seq.ground_truth()
    poses, valid = interpolate_poses(gt, seq.stamps)
    assert valid[index]
    frame = seq.read(index)
    kp = Keypoints(xy.astype(np.float32), desc, np.ones(len(xy), np.float32))
    depth = depth_at_pixels(frame.depth, xy).astype(np.float32)
    return CachedFrame(index, frame.stamp, kp, depth, poses[index]), frame.depth


def dynamic_mask(seq: RGBDSequence, index: int) -> np.ndarray:
    return cv2.imread(str(seq.root / f"dynamic/{seq.records[index].stamp:.6f}.png"), cv2.IMREAD_GRAYSCALE) > 0


@pytest.fixture(scope="module")
def synthetic_pair(synthetic_sequence):
    """A grid of keypoints in frame A; B's keypoints are the exact projections of A's visible ones
    (with slightly noisy descriptors) plus random distractors."""
    seq = RGBDSequence(synthetic_sequence)
    rng = np.random.default_rng(0)
    cam = seq.camera
    xs, ys = np.meshgrid(np.arange(8, cam.width - 8, 6), np.arange(8, cam.height - 8, 6))
    xy_a = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32)
    desc_a = unit_vectors(rng, len(xy_a))
    frame_a, _ = load(seq, FRAME_A, xy_a, desc_a)
    empty_b, depth_b = load(seq, FRAME_B, np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    probe = pair_geometry(frame_a, empty_b, cam.matrix, cam.width, cam.height, depth_b)
    source = np.flatnonzero(probe.visibility_a == VISIBLE)
    distractors = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (300, 2))
    # a distractor right on a projection would be the same 3-D point: keep them away from all projections
    gap = np.linalg.norm(distractors[:, None] - probe.xy_ab[source][None], axis=2).min(1)
    distractors = distractors[gap > 10][:150]
    xy_b = np.concatenate([probe.xy_ab[source] + rng.normal(0, 0.3, (len(source), 2)), distractors])
    desc_b = np.concatenate([desc_a[source] + rng.normal(0, 0.02, (len(source), 128)).astype(np.float32),
                             unit_vectors(rng, len(distractors))])
    frame_b, depth_b = load(seq, FRAME_B, xy_b, desc_b)
    geometry = pair_geometry(frame_a, frame_b, cam.matrix, cam.width, cam.height, depth_b)
    return seq, frame_a, frame_b, geometry, source


def test_interpolated_poses_are_exact_at_stamps_and_halfway_between():
    stamps = np.array([0.0, 1.0])
    poses = np.stack([np.eye(4), make_pose(so3_exp(np.array([0, 0, 0.4])), [1.0, 2.0, 0.0])])
    gt = Trajectory(stamps, poses)
    out, valid = interpolate_poses(gt, np.array([-0.1, 0.0, 0.5, 1.0, 1.1]), max_gap=2.0)
    np.testing.assert_array_equal(valid, [False, True, True, True, False])
    assert not interpolate_poses(gt, np.array([0.5]), max_gap=0.1)[1][0]  # a gap in the ground truth
    np.testing.assert_allclose(out[1], poses[0], atol=1e-12)
    np.testing.assert_allclose(out[3], poses[1], atol=1e-12)
    np.testing.assert_allclose(out[2, :3, 3], [0.5, 1.0, 0.0])
    assert rotation_angle(out[2, :3, :3]) == pytest.approx(0.2)


def test_ground_truth_projection_lands_on_the_same_surface_colour(synthetic_pair):
    """Independent check of the projection conventions: a static point looks the same in both frames."""
    seq, frame_a, _, geometry, source = synthetic_pair
    rgb_a, rgb_b = seq.read(FRAME_A).rgb.astype(float), seq.read(FRAME_B).rgb.astype(float)
    xy_a = frame_a.keypoints.xy[source].round().astype(int)
    xy_b = geometry.xy_ab[source].round().astype(int)
    diff = np.abs(rgb_a[xy_a[:, 1], xy_a[:, 0]] - rgb_b[xy_b[:, 1], xy_b[:, 0]]).mean(1)
    shuffled = np.abs(rgb_a[xy_a[:, 1], xy_a[:, 0]] - np.roll(rgb_b[xy_b[:, 1], xy_b[:, 0]], 37, axis=0)).mean(1)
    assert len(source) > 800
    assert np.median(diff) < 10 and np.median(shuffled) > 3 * np.median(diff)


def test_positives_are_the_true_correspondences(synthetic_pair):
    _, frame_a, frame_b, geometry, source = synthetic_pair
    conf = LabelConfig(max_anchors=10_000)
    labelled = label_pairs(frame_a, frame_b, geometry, conf, np.random.default_rng(1))
    positive = labelled.kind == POSITIVE
    truth = dict(zip(source.tolist(), range(len(source)), strict=True))  # A index -> B index built from it
    assert all(truth.get(a) == b for a, b in zip(labelled.idx_a[positive], labelled.idx_b[positive], strict=True))
    assert positive.sum() >= 0.9 * len(source)
    assert np.all(labelled.label[positive] == 1) and np.all(labelled.label[~positive] == 0)
    # every negative is far from the projection (or its anchor is hidden in B)
    neg = ~positive
    dist = np.linalg.norm(geometry.xy_ab[labelled.idx_a[neg]] - frame_b.keypoints.xy[labelled.idx_b[neg]], axis=1)
    hidden = geometry.visibility_a[labelled.idx_a[neg]] == OCCLUDED
    assert np.all((dist > conf.negative_px) | hidden)
    assert (labelled.kind == 1).sum() > 0 and (labelled.kind == 2).sum() > 0


def test_points_on_the_moving_box_that_left_their_place_are_left_out(synthetic_pair):
    seq, frame_a, _, geometry, _ = synthetic_pair
    xy = frame_a.keypoints.xy.round().astype(int)
    on_box_in_a = dynamic_mask(seq, FRAME_A)[xy[:, 1], xy[:, 0]]
    landed = geometry.xy_ab.round()
    inside = geometry.in_view_a
    on_box_in_b = np.zeros(len(xy), bool)
    on_box_in_b[inside] = dynamic_mask(seq, FRAME_B)[landed[inside, 1].astype(int), landed[inside, 0].astype(int)]
    moved_away = on_box_in_a & inside & ~on_box_in_b  # static-world projection lands on the wall behind
    assert moved_away.sum() >= 20
    assert np.all(geometry.visibility_a[moved_away] == MOVED)
    labelled = label_pairs(frame_a, synthetic_pair[2], geometry, LabelConfig(max_anchors=10_000),
                           np.random.default_rng(2))
    assert not np.isin(labelled.idx_a, np.flatnonzero(moved_away)).any()


def test_keypoint_repeatability_checks_the_ground_truth(synthetic_pair):
    _, _, frame_b, geometry, _ = synthetic_pair
    assert keypoint_repeatability(geometry, frame_b.keypoints.xy) > 0.95
    # a pose error of ~4 px (the grid is 6 px, so a 3 px diagonal shift lands between keypoints)
    assert keypoint_repeatability(geometry, frame_b.keypoints.xy + np.float32(3.0)) < 0.2


def test_time_split_keeps_pairs_inside_their_part():
    conf = SplitConfig(step=2, deltas=[2, 4, 10])
    parts = split_frames(560, conf)
    assert parts["train"][-1] < parts["val"][0] < parts["val"][-1] < parts["test"][0]
    assert parts["test"][0] >= 448 and parts["train"][-1] < 392
    for frames in parts.values():
        for a, b in frame_pairs(frames, conf.deltas):
            assert a in frames and b in frames and b - a in conf.deltas
