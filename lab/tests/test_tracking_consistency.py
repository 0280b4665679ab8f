"""The ground-truth-free consistency check: the fit must prefer the true camera centres, and tracks on real frames
must be one observation per image and geometrically consistent."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.dataset import CAMERA_PRESETS, RGBDSequence
from twohr.geometry import huber_loss, invert_pose, make_pose, rotation_angle, so3_exp
from twohr.pose import observation_residuals
from twohr_lab.tracking.consistency import (
    Tracks,
    build_tracks,
    candidate_trajectories,
    fit_rotations,
    initial_points,
    main,
)

K = CAMERA_PRESETS["bonn"].matrix


def _scene(seed: int = 0, frames: int = 10, points: int = 300, pixel_noise: float = 0.3):
    """Cameras sliding sideways and turning a little, looking at points 2-4 m away, every point seen by all."""
    rng = np.random.default_rng(seed)
    poses = np.stack([make_pose(so3_exp(np.array([0.01 * np.sin(i), 0.02 * i, 0.0])),
                                np.array([0.03 * i, 0.005 * np.cos(i), 0.01 * i])) for i in range(frames)])
    world = np.c_[rng.uniform(-1.2, 1.5, points), rng.uniform(-0.8, 0.8, points), rng.uniform(2.0, 4.0, points)]
    frame, point, xy, depth = [], [], [], []
    for f, pose in enumerate(poses):
        cam = (world - pose[:3, 3]) @ pose[:3, :3]
        uv = cam[:, :2] / cam[:, 2:] * np.diag(K)[:2] + K[:2, 2] + rng.normal(0, pixel_noise, (points, 2))
        frame += [f] * points
        point += list(range(points))
        xy.append(uv)
        depth.append(cam[:, 2] * (1 + rng.normal(0, 0.01, points)))
    return poses, Tracks(np.array(frame), np.array(point), np.vstack(xy), np.concatenate(depth))


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(rotation_angle(np.swapaxes(a, 1, 2) @ b))


def test_rotations_settle_and_the_true_centres_cost_least():
    poses, tracks = _scene()
    start = poses.copy()
    rng = np.random.default_rng(1)
    for pose in start[1:]:
        pose[:3, :3] = so3_exp(rng.normal(0, np.radians(0.5), 3)) @ pose[:3, :3]
    true_fit = fit_rotations(K, start, tracks, depth_noise=0.05)
    assert _rotation_error_deg(true_fit.poses[:, :3, :3], poses[:, :3, :3]).max() < 0.05
    assert 0.2 < true_fit.median_px < 0.5  # the pixel noise that was added, not more
    wobble = start.copy()
    wobble[:, :3, 3] += 0.01 * np.c_[np.sin(np.arange(10)), np.cos(np.arange(10)), np.zeros(10)]
    wobble[0] = start[0]  # the first camera fixes the gauge in both
    wobbled_fit = fit_rotations(K, wobble, tracks, depth_noise=0.05)
    assert wobbled_fit.cost > 1.5 * true_fit.cost


def test_the_fit_scores_what_bundle_adjustment_minimises():
    """Same residuals (pixels, inverse depth over the tracker's depth noise) and the same Huber loss as the BA."""
    poses, tracks = _scene(frames=4, points=80)
    kept, points = initial_points(tracks, poses, K)
    t_cw = invert_pose(poses)[kept.frame]
    cam = (t_cw[:, :3, :3] @ points[kept.point][:, :, None])[:, :, 0] + t_cw[:, :3, 3]
    for depth_noise, huber in ((0.05, 2.0), (0.005, 1.0)):
        res, _ = observation_residuals(K, cam, kept.xy, kept.depth, depth_noise)
        start = fit_rotations(K, poses, tracks, depth_noise, iterations=0, huber=huber)
        assert start.cost == pytest.approx(huber_loss(res, huber).sum(), rel=1e-12)
        assert start.cost_depth == pytest.approx(huber_loss(res[:, 2], huber).sum(), rel=1e-12)
        assert fit_rotations(K, poses, tracks, depth_noise, huber=huber).cost < start.cost


def test_controls_move_the_estimate_as_far_as_the_ground_truth_does():
    poses, _ = _scene()
    truth = poses.copy()
    truth[:, :3, 3] += np.c_[np.linspace(0, 0.02, 10), np.zeros(10), 0.01 * np.sin(np.arange(10))]
    candidates = candidate_trajectories(poses, truth)
    moved = {name: np.sqrt(np.mean(np.sum((c[:, :3, 3] - poses[:, :3, 3]) ** 2, 1))) for name, c in candidates.items()}
    assert moved["estimate"] == 0
    assert moved["ground truth"] > 0.005
    for name in ("control: difference axes permuted", "control: difference negated"):
        assert moved[name] == pytest.approx(moved["ground truth"], rel=1e-9)
    assert moved["control: difference reversed in time"] == pytest.approx(moved["ground truth"], rel=0.5)


def test_tracks_on_real_frames_are_one_observation_per_image(dev_sequence):
    sequence = RGBDSequence(dev_sequence)
    frames = [sequence.read(i) for i in (0, 4, 8, 12)]
    grays = [np.asarray(f.rgb.mean(axis=2), np.uint8) for f in frames]
    tracks = build_tracks(grays, [f.depth for f in frames], [None] * len(frames), max_gap=3)
    assert tracks.num_points > 100
    for p in range(tracks.num_points):
        seen = tracks.frame[tracks.point == p]
        assert len(seen) >= 3 and len(np.unique(seen)) == len(seen)
    assert (tracks.depth > 0).mean() > 0.5


def test_bad_run_folder_is_a_clear_error(tmp_path, capsys):
    assert main(["--run", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "not a run folder" in capsys.readouterr().err
