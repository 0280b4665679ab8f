"""The keyframe policy: keyframes by the map's own evidence (tracked ratio, close points, time), a queue that sheds
stale jobs and never the newest, and culling that keeps a camera going round in one place at one working set."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.config import TrackerConfig, load_config
from twohr.dataset import RGBDSequence
from twohr.evaluation import associate_trajectories
from twohr.geometry import invert_pose
from twohr.trajectory import Trajectory
from twohr_app.pipeline import local_stages
from twohr_services.tracker.keyframe_policy import Evidence, KeyframeQueue, may_queue, redundant, weakness
from twohr_services.tracker.schedule import build_schedule

CONF = TrackerConfig()


def test_a_frame_is_weak_below_the_ratio_of_its_reference_in_all_or_close_points():
    ratio = CONF.keyframe_tracked_ratio
    assert weakness(Evidence(100, 100, 50, 50, 0.1), CONF) is None
    assert weakness(Evidence(int(ratio * 100), 100, 50, 50, 0.1), CONF) is None  # at the ratio: still enough
    assert "of the reference keyframe's 100" in weakness(Evidence(int(ratio * 100) - 1, 100, 50, 50, 0.1), CONF)
    assert "nearer than" in weakness(Evidence(95, 100, 30, 50, 0.1), CONF)  # the near points left the view
    assert weakness(Evidence(95, 100, 0, 0, 0.1), CONF) is None  # nothing near to lose
    depth = np.array([0.0, 1.0, 2.9, 3.1, 7.0])
    assert Evidence.of(5, depth, (5, 2), 0.2, CONF).close == 2


def test_time_only_lets_a_weak_frame_wait_behind_a_busy_worker():
    weak = Evidence(60, 100, 60, 60, 0.2)
    assert not may_queue(weak, CONF)
    assert "1.0 s old" in weakness(Evidence(100, 100, 60, 60, CONF.keyframe_max_interval_s), CONF)
    assert may_queue(Evidence(60, 100, 60, 60, CONF.keyframe_max_interval_s), CONF)
    assert may_queue(Evidence(20, 100, 20, 60, 0.2), CONF)  # very weak: at once


def test_the_queue_sheds_what_a_newer_job_makes_redundant_and_never_the_newest():
    queue: KeyframeQueue[str] = KeyframeQueue(3, CONF)
    view_a, view_b = np.arange(100), np.arange(1000, 1100)
    queue.push("a1", view_a)
    queue.push("a2", view_a[10:])  # still tracks 90 % of a1's landmarks: a1 is stale
    assert len(queue) == 1 and queue.shed == 1
    queue.push("b", view_b)  # another view (a fast pan): both wait
    queue.push("lost1", None)
    assert len(queue) == 3 and queue.shed == 1
    queue.push("lost2", None)  # the newest look for the camera wins; the views before the loss stay
    assert len(queue) == 3 and queue.shed == 2
    queue.push("c", np.arange(2000, 2100))  # tracking again: the lost job is stale
    assert [queue.pop() for _ in range(3)] == ["a2", "b", "c"] and queue.pop() is None
    full: KeyframeQueue[int] = KeyframeQueue(2, CONF)
    for n in range(5):  # five different views: the oldest go, the newest always stays
        full.push(n, np.arange(n * 100, n * 100 + 100))
    assert [full.pop(), full.pop()] == [3, 4] and full.shed == 3
    assert redundant(np.zeros(0, np.int64), view_a, CONF)  # a job that tracked nothing holds no view


def _room(spec_update: dict):
    """A synthetic room without movers (seed 3), the camera moving as ``spec_update`` says."""
    from twohr.synthetic import SyntheticSpec

    return SyntheticSpec(occluders=0, seed=3, **spec_update)


def _run(synthetic_room, spec_update: dict, settings: dict | None = None, every: int = 0):
    """Run the keyframes schedule (synchronous, ORB) over a synthetic room without movers (rendered once per
    session: the runs of one room differ in their settings alone); returns the schedule, each frame's keyframe
    evidence, every ``every`` frames the map's working set, and the refined trajectory's error (m,
    :func:`_error_from_first`)."""
    sequence = RGBDSequence(synthetic_room(_room(spec_update)))
    config = load_config(None, {"detector.features": "orb", "yolo.enabled": False, "matcher.method": "mutual_nn",
                                "pipeline.synchronous": True, "tracker.depth_noise": 0.005, **(settings or {})})
    schedule = build_schedule(config, sequence.camera, local_stages(config, sequence.camera))
    evidence, sets = [], []
    for frame in sequence.frames():
        result, _ = schedule.process(frame)
        evidence.append(schedule.frames.keyframe_evidence(result))
        if every and frame.index % every == every - 1:
            sets.append(schedule.map.working_set())
    schedule.finish()
    return schedule, evidence, sets, _error_from_first(sequence.ground_truth(), schedule.trajectory())


def _error_from_first(gt: Trajectory, est: Trajectory) -> float:
    """RMS position error (m) of the poses relative to the first frame's: a camera that only turns gives Umeyama
    alignment nothing to align, so each trajectory is taken from its own first pose."""
    gt, est = associate_trajectories(gt, est, 0.02)
    relative = [invert_pose(invert_pose(gt.poses[0]) @ g) @ invert_pose(est.poses[0]) @ e
                for g, e in zip(gt.poses, est.poses, strict=True)]
    return float(np.sqrt(np.mean([np.sum(r[:3, 3] ** 2) for r in relative])))


def test_a_still_camera_adds_no_keyframes(synthetic_room):
    schedule, evidence, _, _ = _run(synthetic_room, {"frames": 75, "motion": "still"})
    # the first map; then a job every keyframe_max_interval_s (1 s), which finds the view held: no keyframe
    assert [(job.index, job.keyframe) for job in schedule.keyframe_log] == [(0, True), (30, False), (60, False)]
    assert all(e is not None and weakness(e, CONF) is None for n, e in enumerate(evidence[1:], 1) if n not in (30, 60))
    assert len(schedule.map.keyframes) == 1


PAN = {"frames": 60, "motion": "pan", "pan_deg": 60}


@pytest.fixture(scope="module")
def pans(synthetic_room):
    return {ratio: _run(synthetic_room, PAN, {"tracker.keyframe_tracked_ratio": ratio}) for ratio in (0.75, 0.5)}


def test_a_pan_adds_a_keyframe_where_its_tracks_fall_below_the_ratio(pans):
    schedule, evidence, _, _ = pans[0.75]
    jobs = [job.index for job in schedule.keyframe_log]
    assert len(jobs) >= 4 and all(job.keyframe for job in schedule.keyframe_log), jobs  # 0, 17, 28, 39, 42, 52 here
    for index in jobs[1:]:  # each at the first weak frame since the keyframe before it
        asked = evidence[index]
        assert asked.inliers < 0.75 * asked.reference or asked.close < 0.75 * asked.reference_close, (index, asked)
        assert weakness(evidence[index - 1], CONF) is None, (index, evidence[index - 1])
    fewer = [job.index for job in pans[0.5][0].keyframe_log]
    assert len(fewer) < len(jobs), (fewer, jobs)  # a lower ratio waits for weaker tracks


SWEEPS = {"frames": 360, "motion": "pan", "pan_deg": 60, "sweeps": 12}


@pytest.fixture(scope="module")
def sweeps(synthetic_room):
    """Twelve sweeps of the same 60 degrees, the working set every 30 frames (a sweep)."""
    return _run(synthetic_room, SWEEPS, every=30)


def test_a_camera_going_round_one_place_stops_growing_its_working_set(synthetic_room, sweeps):
    """Twelve sweeps of the same 60 degrees: the first ones map it; once unconfirmed landmarks are retired and
    redundant keyframes culled, the working set stays as it is for the last third (12 keyframes, about 2,650
    landmarks here). Without landmark culling the revisits' keyframes stay apart from the older ones: twice the
    keyframes, and twice the working set (39 and 26 here)."""
    culled, _, sets, _ = sweeps
    live = [s["live_keyframes"] for s in sets]
    assert live[-1] <= live[7] + 1, live  # 12 or 13 from sweep 8 on here
    assert max(s["live_landmarks"] for s in sets[8:]) < 1.1 * sets[7]["live_landmarks"], sets
    assert sets[-1]["culled"] >= 4 and live[-1] < sets[-1]["keyframes"], sets[-1]
    _, _, kept, _ = _run(synthetic_room, SWEEPS, {"tracker.landmark_culling": False}, every=30)
    assert kept[-1]["live_keyframes"] > 1.5 * live[-1], (kept[-1], sets[-1])
    assert kept[-1]["keyframes"] > 1.5 * sets[-1]["keyframes"], (kept[-1], sets[-1])
    for k in range(len(culled.map.keyframes)):  # a culled keyframe keeps its pose, for the frames kept against it
        assert np.isfinite(culled.map.keyframe_poses[k]).all()


def test_new_landmarks_fill_the_rows_of_retired_ones_and_the_map_stays_as_accurate(synthetic_room, sweeps):
    """The same twelve sweeps: the rows of retired landmarks that nothing refers to any more are filled again, so
    the landmark arrays stop growing while landmarks are still made (61 rows for 332 landmarks in the last third
    here); no keyframe observes a free row nor does a frame kept for refinement, and the refined trajectory is as
    accurate as with every row kept."""
    reused, _, sets, error = sweeps
    rows, made = [s["landmark_rows"] for s in sets], [s["landmarks"] for s in sets]
    assert made[-1] - made[7] >= 100, made  # the last third still makes landmarks (332 here) ...
    assert rows[-1] - rows[7] <= 0.5 * (made[-1] - made[7]), (rows, made)  # ... mostly in rows retired ones left
    world = reused.map
    free = world.landmarks.free
    assert len(free) == len(np.unique(free)) and world.landmarks.bad[free].all()
    observed = np.concatenate([kf.landmark_ids for kf in world.keyframes])
    assert not np.isin(observed[observed >= 0], free).any()
    assert not np.isin(reused.record.held_landmarks(), free).any()
    _, _, every_row, error_every_row = _run(synthetic_room, SWEEPS, {"tracker.reuse_landmark_rows": False}, every=30)
    assert every_row[-1]["landmark_rows"] == every_row[-1]["landmarks"] > rows[-1], (every_row[-1], sets[-1])
    assert error <= 1.2 * error_every_row + 0.001, (error, error_every_row)


def test_a_slow_mapping_worker_delays_keyframes_rather_than_refusing_them(synthetic_room, pans):
    """A live camera at 30 Hz whose keyframe jobs take 5 frames each (the detector made slow, as on a short CPU):
    the weak frames wait in the queue, stale ones are shed, and the pan gets about the keyframes a mapper that is
    never busy gives it (6 here)."""
    import time

    from twohr_services.tracker.stages import Stages

    sequence = RGBDSequence(synthetic_room(_room(PAN)))  # the pan of ``pans``
    config = load_config(None, {"detector.features": "orb", "yolo.enabled": False, "matcher.method": "mutual_nn",
                                "tracker.depth_noise": 0.005})
    local = local_stages(config, sequence.camera)

    def slow_detect(frame):
        time.sleep(5 / 30)
        return local.detect(frame)

    schedule = build_schedule(config, sequence.camera, Stages(slow_detect, None, local.match), live=True)
    start = time.perf_counter()
    for n, frame in enumerate(sequence.frames()):
        time.sleep(max(0.0, start + n / 30 - time.perf_counter()))  # the camera's pace
        schedule.process(frame)
    schedule.finish()
    made = sum(job.keyframe for job in schedule.keyframe_log)
    never_busy = sum(job.keyframe for job in pans[0.75][0].keyframe_log)
    assert made >= never_busy - 1, (made, never_busy, [job.index for job in schedule.keyframe_log])
    assert max(job.lag_frames for job in schedule.keyframe_log) >= 5  # it was busy: the jobs came back late


def test_a_freed_row_takes_a_new_landmark_whole_and_keeps_the_order_landmarks_were_made():
    from twohr_services.tracker.map import Landmarks

    landmarks = Landmarks()
    first = landmarks.add(np.arange(9.0).reshape(3, 3), np.ones((3, 4), np.float32))
    landmarks.accepted[:] = [5, 0, 0]
    landmarks.rejected[1] = 4
    landmarks.bad[1] = True
    landmarks.free = np.array([1])
    again = landmarks.add(np.full((2, 3), 7.0))  # one into the free row, one appended; no descriptors yet
    assert first.tolist() == [0, 1, 2] and again.tolist() == [1, 3] and len(landmarks) == 4 and landmarks.made == 5
    assert (landmarks.positions[1] == 7).all() and not landmarks.bad[1] and not landmarks.described[1]
    assert landmarks.accepted[1] == landmarks.rejected[1] == 0 and (landmarks.descriptors[1] == 0).all()
    assert landmarks.born.tolist() == [0, 3, 2, 4] and len(landmarks.free) == 0
    # most accepted first; among equals the older one (row 2, made before row 1 was filled again)
    assert landmarks.most_accepted(np.array([3, 1, 2, 0])).tolist() == [0, 2, 1, 3]
