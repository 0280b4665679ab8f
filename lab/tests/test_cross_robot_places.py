"""The co-mapping study (:mod:`twohr_lab.places.robots`) on real frames: robot a maps the dev frames 0-199, robot b
the backwards variant's frames 200-399 (dev frames 359 down to 160: its last 40 frames cross ground a mapped). b's
keyframes are found in a's map, every verified match agrees with the ground truth, and k of them merge b's map into
a's; a robot in another scene (rendered, its own camera) is never merged."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.config import PipelineConfig
from twohr.dataset import RGBDSequence
from twohr.synthetic import SyntheticSpec, generate
from twohr_app.pipeline import run_sequence
from twohr_lab.places.robots import consistent_merge, cross_matches, pose_gap, score_matches, true_T_ab
from twohr_lab.tracking.backwards import backwards
from twohr_services.matcher.core import build_matcher


@pytest.fixture(scope="module")
def robot_a(dev_sequence):
    sequence = RGBDSequence(dev_sequence)
    return sequence, run_sequence(sequence, PipelineConfig(), start=0, stop=200, progress=False)


def _truth(sequence: RGBDSequence):
    return sequence.ground_truth(sequence.default_gt_extrinsic())


def test_a_second_robot_is_found_in_the_first_robots_map_and_merged_where_the_truth_puts_it(robot_a, dev_sequence,
                                                                                            tmp_path):
    sequence_a, run_a = robot_a
    sequence_b = RGBDSequence(backwards(dev_sequence, tmp_path))
    config = PipelineConfig()
    run_b = run_sequence(sequence_b, config, start=200, stop=400, progress=False)
    matches = cross_matches(run_a.map, run_b.map, sequence_b.camera.matrix, config, build_matcher(config.matcher))
    T_true = true_T_ab(run_a.trajectory, _truth(sequence_a), run_b.trajectory, _truth(sequence_b))
    errors = score_matches(matches, run_b.map, T_true)
    print(f"{len(matches)} of {len(run_b.map.keyframes)} keyframes of b found in a's map "
          f"({len(run_a.map.keyframes)} keyframes); errors (m, deg): {[(round(m, 3), round(d, 1)) for m, d in errors]}")
    assert len(matches) >= 3, "b's keyframes over a's ground were not found"
    # every accepted cross-robot match lies within 0.3 m and 15 deg of where the ground truth puts it
    assert all(m <= 0.3 and d <= 15 for m, d in errors), errors
    merged = consistent_merge(matches, k=3)
    assert merged is not None
    end, T_ab = merged
    into = matches[end].b_stamp - run_b.trajectory.stamps[0]
    print(f"merged at b's keyframe {matches[end].b_keyframe}, {into:.2f} s into b's run")
    metres, degrees = pose_gap(T_ab, T_true)
    # b's map falls on a's where the truth puts it: within 0.1 m at b's keyframes' centre, and 3 deg
    centre = np.mean(run_b.map.keyframe_poses[:, :3, 3], axis=0)
    shift = np.linalg.norm((T_ab[:3, :3] - T_true[:3, :3]) @ centre + T_ab[:3, 3] - T_true[:3, 3])
    assert shift <= 0.1 and degrees <= 3.0, (metres, degrees, shift)


def test_a_robot_in_another_scene_is_never_merged(robot_a, tmp_path):
    _, run_a = robot_a
    other = RGBDSequence(generate(tmp_path / "other", SyntheticSpec(frames=60, width=640, height=480, seed=7)))
    config = PipelineConfig()
    run_b = run_sequence(other, config, progress=False)
    matches = cross_matches(run_a.map, run_b.map, other.camera.matrix, config, build_matcher(config.matcher))
    assert consistent_merge(matches, k=3) is None, [(m.b_keyframe, m.a_keyframe, m.inliers) for m in matches]
