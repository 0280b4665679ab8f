"""Speed (and accuracy) of the keyframe tracker against the simplest baseline, measured in the same run.

The baseline is plain frame-to-frame RGB-D VO: mutual-NN matches to the previous frame, back-projected
with its depth, RANSAC PnP, no map and no refinement (the "simple system" of ../shared/README.md). Both
get the same keypoints, with the pipeline's dynamic mask applied (the front end of ``twohr run``, run
once and shared through :class:`~twohr_lab.bench.steps.front_cache.FrontCache`), so only the back ends differ::

    .venv/bin/python -m twohr_lab.tracking.vo_bench --frames 560 --repeats 3 --out runs/vo_bench

Reports the median per-frame milliseconds of each over the repeats, their ratio, and both ATEs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from twohr.config import TrackerConfig, load_config
from twohr.dataset import RGBDSequence
from twohr.errors import TwohrError
from twohr.evaluation import evaluate
from twohr.features import drop_masked, mutual_nn
from twohr.geometry import backproject, invert_pose
from twohr.paths import DEV_SEQUENCE
from twohr.pose import pnp_ransac, sample_depth
from twohr.trajectory import Trajectory
from twohr_services.tracker.tracking import Tracker
from twohr_services.tracker.trajectory import AnchoredTrajectory

from ..bench.steps.front_cache import FrontCache
from ..stamp import provenance


def frame_to_frame_vo(camera, frames, conf: TrackerConfig) -> tuple[np.ndarray, list[float]]:
    """Poses (camera-to-world) and per-frame milliseconds of the baseline VO."""
    K = camera.matrix
    poses, times = [np.eye(4)], []
    previous = None
    for kps, depth in frames:
        start = time.perf_counter()
        z = sample_depth(depth, kps.xy.astype(np.float64), conf.min_depth, conf.max_depth, conf.depth_edge_ratio)
        if previous is not None:
            prev_kps, prev_z = previous
            matches = mutual_nn(prev_kps.descriptors, kps.descriptors)
            has_depth = prev_z[matches.idx_a] > 0
            a, b = matches.idx_a[has_depth], matches.idx_b[has_depth]
            points = backproject(prev_kps.xy[a].astype(np.float64), prev_z[a], K)
            T_cw, inliers = pnp_ransac(K, points, kps.xy[b].astype(np.float64), conf.ransac_reprojection_px,
                                       conf.ransac_iterations)
            tracked = T_cw is not None and inliers.sum() >= conf.min_inliers
            pose = poses[-1] @ invert_pose(T_cw) if tracked else poses[-1]
            poses.append(pose)
        previous = (kps, z)
        times.append((time.perf_counter() - start) * 1000)
    return np.asarray(poses[: len(frames)]), times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.tracking.vo_bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", default=DEV_SEQUENCE, help="TUM-layout RGB-D folder with ground truth")
    parser.add_argument("--config", default=None, help="YAML pipeline config (its front end and tracker)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    parser.add_argument("--start", type=int, default=0, help="first frame")
    parser.add_argument("--frames", type=int, default=None, help="process at most this many frames")
    parser.add_argument("--step", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each back end (median reported)")
    parser.add_argument("--out", default="runs/vo_bench", help="where to write bench.json (default runs/vo_bench)")
    args = parser.parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        config = load_config(args.config, args.set)
        sequence = RGBDSequence(args.sequence)
        if not sequence.has_ground_truth():
            raise TwohrError(f"{sequence.root} has no groundtruth.txt: the bench reports ATE")
        if args.start < 0 or args.step < 1 or args.repeats < 1 or (args.frames is not None and args.frames < 1):
            raise TwohrError("--start must be >= 0; --step, --frames and --repeats >= 1")
    except TwohrError as exc:
        print(f"vo_bench: error: {exc}", file=sys.stderr)
        return 2
    stop = len(sequence) if args.frames is None else min(len(sequence), args.start + args.frames * args.step)
    fronts = FrontCache().outputs(sequence, config, stop, True, args.start, args.step)
    frames, stamps = [], []
    for frame in sequence.frames(args.start, stop, args.step):
        front = fronts[frame.index]
        frames.append((front.keypoints if front.mask is None else drop_masked(front.keypoints, front.mask),
                       frame.depth))
        stamps.append(frame.stamp)
    gt = sequence.ground_truth(sequence.default_gt_extrinsic())
    conf = config.tracker
    tracker_ms, baseline_ms = [], []
    for _ in range(args.repeats):
        # interleaved, so both back ends see the same load on a shared machine
        tracker = Tracker(sequence.camera, conf, match=mutual_nn)
        record = AnchoredTrajectory(conf)
        start = time.perf_counter()
        for stamp, (kps, depth) in zip(stamps, frames, strict=True):
            result = tracker.track(stamp, kps, depth)
            record.add(stamp, result.pose, result.tracked, len(tracker.keyframes) - 1, tracker.keyframe_poses)
        tracker_ms.append((time.perf_counter() - start) * 1000 / len(frames))
        baseline_poses, times = frame_to_frame_vo(sequence.camera, frames, conf)
        baseline_ms.append(float(np.sum(times)) / len(frames))
    extrinsic = sequence.default_gt_extrinsic()
    tracker_report, _ = evaluate(gt, record.trajectory(tracker.keyframe_poses), gt_extrinsic=extrinsic)
    baseline_report, _ = evaluate(gt, Trajectory(np.asarray(stamps), baseline_poses), gt_extrinsic=extrinsic)
    summary = {
        "provenance": provenance(argv, "python -m twohr_lab.tracking.vo_bench"),
        "frames": len(frames),
        "repeats": args.repeats,
        "tracker_ms_per_frame_median": float(np.median(tracker_ms)),
        "baseline_vo_ms_per_frame_median": float(np.median(baseline_ms)),
        "ratio_tracker_to_baseline": float(np.median(tracker_ms) / np.median(baseline_ms)),
        "tracker_ms_runs": tracker_ms,
        "baseline_ms_runs": baseline_ms,
        "tracker_ate_rmse": tracker_report.ate.rmse,
        "baseline_vo_ate_rmse": baseline_report.ate.rmse,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
