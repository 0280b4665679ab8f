"""Speed (and accuracy) of the tracker against the simplest baseline, measured in the same run.

The baseline is plain frame-to-frame RGB-D VO: mutual-NN matches to the previous frame, back-projected
with its depth, RANSAC PnP, no map and no refinement (the "simple system" of ../shared/README.md). Both
get the same cached keypoints and person-box masks from ``dev_run``, so only the back ends differ::

    .venv/bin/python -m twohr_services.tracker.bench --frames 560 --repeats 3

Reports the median per-frame milliseconds of each over the repeats, their ratio, and both ATEs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from twohr.config import TrackerConfig
from twohr.errors import TwohrError
from twohr.evaluation import evaluate
from twohr.geometry import backproject, invert_pose
from twohr.trajectory import Trajectory

from .dev_run import RESULTS, load_inputs, mutual_nn_match, outside_boxes
from .dev_run import build_parser as dev_parser
from .optim import pnp_ransac, sample_depth


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
            matches = mutual_nn_match(prev_kps.descriptors, kps.descriptors)
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
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                     parents=[dev_parser()], add_help=False, conflict_handler="resolve")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each back end (median reported)")
    parser.add_argument("--out", default=str(RESULTS / "bench"), help="where to write bench.json")
    args = parser.parse_args(argv)
    args.quiet = True
    try:
        sequence, cached = load_inputs(args)
    except TwohrError as exc:
        print(f"bench: error: {exc}", file=sys.stderr)
        return 2
    from .core import Tracker

    frames, stamps = [], []
    for k in range(len(cached.frames)):
        frame = sequence.read(int(cached.frames[k]))
        kps = cached.keypoints(k)
        if not args.no_mask:
            kps = kps.subset(outside_boxes(kps.xy, cached.person_boxes(k, args.box_score), args.box_margin))
        frames.append((kps, frame.depth))
        stamps.append(frame.stamp)
    gt = sequence.ground_truth(sequence.default_gt_extrinsic())
    conf = TrackerConfig()
    tracker_ms, baseline_ms = [], []
    for _ in range(args.repeats):
        # interleaved, so both back ends see the same load on a shared machine
        tracker = Tracker(sequence.camera, conf, match=mutual_nn_match)
        start = time.perf_counter()
        for stamp, (kps, depth) in zip(stamps, frames, strict=True):
            tracker.track(stamp, kps, depth)
        tracker_ms.append((time.perf_counter() - start) * 1000 / len(frames))
        baseline_poses, times = frame_to_frame_vo(sequence.camera, frames, conf)
        baseline_ms.append(float(np.sum(times)) / len(frames))
    tracker_report, _ = evaluate(gt, tracker.trajectory())
    baseline_report, _ = evaluate(gt, Trajectory(np.asarray(stamps), baseline_poses))
    summary = {
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
