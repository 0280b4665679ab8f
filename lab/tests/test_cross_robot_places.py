"""The map server's core on real frames (:mod:`twohr_lab.places.robots`): robot a maps the dev frames 0-199, robot b
the backwards variant's frames 200-399 (dev frames 359 down to 160: its last 40 frames cross ground a mapped), their
keyframes handed to one shared map as two robots started together would send them. b's keyframes are found in a's
map, every verified match agrees with the ground truth, and b is merged where the truth puts it; a robot in another
scene (rendered, its own camera) is never merged, over 3 scenes."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.config import PipelineConfig
from twohr.dataset import RGBDSequence
from twohr.synthetic import SyntheticSpec, generate
from twohr_app.pipeline import run_sequence
from twohr_lab.places.robots import Robot, replay_shared, score_matches, true_T_ab
from twohr_lab.tracking.backwards import backwards
from twohr_services.mapserver.core import pose_gap


@pytest.fixture(scope="module")
def robot_a(dev_sequence):
    sequence = RGBDSequence(dev_sequence)
    return sequence, run_sequence(sequence, PipelineConfig(), start=0, stop=200, progress=False)


def _truth(sequence: RGBDSequence):
    return sequence.ground_truth(sequence.default_gt_extrinsic())


def _robot(name: str, run, sequence: RGBDSequence) -> Robot:
    return Robot(name, run.map.arrays(), sequence.camera, float(run.trajectory.stamps[0]))


def test_a_second_robot_is_found_in_the_first_robots_map_and_merged_where_the_truth_puts_it(robot_a, dev_sequence,
                                                                                            tmp_path):
    sequence_a, run_a = robot_a
    sequence_b = RGBDSequence(backwards(dev_sequence, tmp_path))
    run_b = run_sequence(sequence_b, PipelineConfig(), start=200, stop=400, progress=False)
    shared, events = replay_shared([_robot("a", run_a, sequence_a), _robot("b", run_b, sequence_b)])
    b = shared.submaps["b"]
    T_true = true_T_ab(run_a.trajectory, _truth(sequence_a), run_b.trajectory, _truth(sequence_b))
    errors = score_matches(b.matches, b.poses, T_true)
    print(f"{len(b.matches)} of {len(b)} keyframes of b found in a's map ({len(shared.submaps['a'])} keyframes); "
          f"errors (m, deg): {[(round(m, 3), round(d, 1)) for m, d in errors]}")
    assert len(b.matches) >= 3, "b's keyframes over a's ground were not found"
    # every accepted cross-robot match lies within 0.3 m and 15 deg of where the ground truth puts it
    assert all(m <= 0.3 and d <= 15 for m, d in errors), errors
    merged = [e for e in events if e.robot == "b" and e.kind == "merged"]
    assert [e.kind for e in events if e.robot == "a"] == ["defines"] and len(merged) == 1, events
    into = merged[0].stamp - run_b.trajectory.stamps[0]
    print(f"merged at b's keyframe {merged[0].keyframes}, {into:.2f} s into b's run, search {merged[0].ms:.0f} ms; "
          f"{sum(e.kind == 'refined' for e in events)} refinements")
    # b's map falls on a's where the truth puts it: within 0.1 m at b's keyframes' centre, and 3 deg
    T = b.T
    metres, degrees = pose_gap(T, T_true)
    centre = np.mean(b.poses[:, :3, 3], axis=0)
    shift = np.linalg.norm((T[:3, :3] - T_true[:3, :3]) @ centre + T[:3, 3] - T_true[:3, 3])
    assert shift <= 0.1 and degrees <= 3.0, (metres, degrees, shift)


@pytest.mark.parametrize("seed", [7, 8, 9])
def test_a_robot_in_another_scene_is_never_merged(robot_a, tmp_path, seed):
    sequence_a, run_a = robot_a
    other = RGBDSequence(generate(tmp_path / "other", SyntheticSpec(frames=40, width=640, height=480, seed=seed)))
    run_b = run_sequence(other, PipelineConfig(), progress=False)
    shared, events = replay_shared([_robot("a", run_a, sequence_a), _robot("b", run_b, other)])
    b = shared.submaps["b"]
    assert b.T is None and [e.robot for e in events] == ["a"], [(m.keyframe, m.candidate, m.inliers)
                                                                  for m in b.matches]
