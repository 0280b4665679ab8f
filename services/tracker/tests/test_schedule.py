"""The tracker room's interfaces: one Schedule whichever the mode, one Map that owns the keyframe poses, and the
motion model's correction by a late keyframe job."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.config import load_config
from twohr.dataset import RGBDSequence
from twohr.evaluation import evaluate, static_trajectory
from twohr.geometry import make_pose
from twohr_app.pipeline import local_stages
from twohr_services.tracker.every_frame import EveryFrameSchedule
from twohr_services.tracker.keyframe_schedule import KeyframePipeline
from twohr_services.tracker.map import Map
from twohr_services.tracker.motion import MotionModel
from twohr_services.tracker.schedule import Schedule, build_schedule

SCHEDULE_MEMBERS = [name for name in dir(Schedule) if not name.startswith("_")] + ["keyframe_log", "mask"]


@pytest.mark.parametrize(("mode", "kind"), [("keyframes", KeyframePipeline), ("every_frame", EveryFrameSchedule)])
def test_both_schedules_answer_the_same_interface(static_synthetic_sequence, mode, kind):
    """Each mode's schedule tracks synthetic frames through the Schedule interface alone: poses near the truth,
    a map that grows with a new version, and a refined trajectory of every frame."""
    sequence = RGBDSequence(static_synthetic_sequence)
    config = load_config(None, {"detector.features": "orb", "yolo.enabled": False, "matcher.method": "mutual_nn",
                                "pipeline.synchronous": True, "pipeline.mode": mode, "tracker.depth_noise": 0.005})
    schedule = build_schedule(config, sequence.camera, local_stages(config, sequence.camera))
    assert isinstance(schedule, kind)
    assert all(hasattr(schedule, name) for name in SCHEDULE_MEMBERS), SCHEDULE_MEMBERS
    first = schedule.map_snapshot()
    results = [schedule.process(frame)[0] for frame in sequence.frames(0, 20)]
    schedule.finish()
    later = schedule.map_snapshot(since=first.version)
    assert later.version > first.version and len(later.points) > 50
    assert len(later.keyframe_stamps) == len(later.keyframe_poses) == later.version
    assert schedule.map_snapshot(since=later.version) is None
    schedule.refine()
    trajectory = schedule.trajectory()
    assert len(trajectory) == len(results) == 20
    report, _ = evaluate(sequence.ground_truth(), trajectory)
    static, _ = evaluate(sequence.ground_truth(), static_trajectory(trajectory.stamps))
    assert report.matched == 20 and report.ate.rmse < 0.015 and report.ate.rmse < static.ate.rmse / 5, (
        report.ate.rmse, static.ate.rmse)


def test_a_snapshot_is_a_copy_and_keyframes_hold_no_pose(synthetic_sequence):
    sequence = RGBDSequence(synthetic_sequence)
    world = Map(sequence.camera, load_config().tracker)
    keyframe = world.add_keyframe(0.0, np.eye(4), np.zeros((3, 2)), np.ones(3), np.arange(3))
    world.landmarks.add(np.ones((3, 3)), np.zeros((3, 8)))
    snapshot = world.snapshot()
    world.keyframe_poses[0, 0, 3] = 1.0
    world.landmarks.positions[0] = 5.0
    assert snapshot.version == 1 and snapshot.keyframe_poses[0, 0, 3] == 0.0 and list(snapshot.keyframe_stamps) == [0.0]
    assert snapshot.landmark_positions[0, 0] == 1.0
    assert not hasattr(keyframe, "pose")  # the map's array is the only copy


def test_a_late_keyframe_measurement_corrects_a_lost_motion_model():
    motion = MotionModel()
    motion.tracked(0.0, np.eye(4))
    motion.advance(0.0, np.eye(4))
    for stamp in (0.1, 0.2):
        motion.coast()
        motion.advance(stamp, make_pose(np.eye(3), [0.5, 0, 0]))  # coasting off somewhere wrong
    measured = make_pose(np.eye(3), [0.02, 0, 0])
    motion.correct(measured, 0.1)  # the keyframe job of frame 0.1 found the camera again
    assert np.array_equal(motion.last_pose, measured) and motion.lost_frames == 2
    motion.correct(measured, 0.2)  # ... and of the latest frame: tracked again
    assert motion.lost_frames == 0 and np.array_equal(motion.good_pose, measured)
    restart = make_pose(np.eye(3), [1.0, 0, 0])
    motion.correct(restart, 0.3, new_map=True)
    assert np.array_equal(motion.last_pose, restart) and motion.last_stamp == 0.3
    assert np.array_equal(motion.velocity, np.eye(4))


def test_a_keyframe_job_asks_for_the_mask_only_when_it_carries_none(synthetic_sequence):
    """Detection and the dynamic mask are asked at once; a job that carries its frame's own mask asks yolo no
    more, and its keypoints are masked all the same; the job's whole latency is reported."""
    from twohr_services.tracker.mapper import KeyframeJob, Mapper
    from twohr_services.tracker.stages import Stages
    from twohr_services.tracker.tracking import Tracker

    sequence = RGBDSequence(synthetic_sequence)
    config = load_config(None, {"detector.features": "orb", "yolo.enabled": False, "matcher.method": "mutual_nn"})
    local = local_stages(config, sequence.camera)
    frame = next(iter(sequence.frames(0, 1)))
    left_half = np.zeros(frame.depth.shape, bool)
    left_half[:, : frame.depth.shape[1] // 2] = True
    asked: list[int] = []

    def dynamic_mask(asked_frame):
        asked.append(asked_frame.index)
        return left_half, 1

    stages = Stages(local.detect, dynamic_mask, local.match)
    for carried in (None, left_half):
        mapper = Mapper(config, Tracker(sequence.camera, config.tracker), stages)
        update = mapper(KeyframeJob(frame, np.eye(4), mask=carried))
        mapper.close()
        kept = update.result.observed_xy
        assert update.keyframe_id == 0 and len(kept) > 20
        assert (kept[:, 0] >= frame.depth.shape[1] // 2 - 1).all()  # no keypoint under the mask
        assert update.timings["job"] >= update.timings["mapping"] > 0
    assert asked == [frame.index]  # once, for the job without a mask
