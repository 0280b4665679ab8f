"""``twohr bench`` (no study flag) or ``twohr bench throughput``: FPS, per-stage ms (median, p90) and peak RSS of
the pipeline over ``--frames`` frames (default 60), ``--runs`` times, each run paired with an ORB baseline run for a
ratio, and ORB-SLAM3 RGB-D beside them where pyorbslam3 is installed. bench.json: ``throughput``."""

from __future__ import annotations

import argparse

NAME = "throughput"
HELP = "FPS, per-stage latency and peak RSS of the pipeline, against an ORB baseline (the default study)"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    """Throughput takes the common options alone; it is what ``twohr bench`` runs without a study's flag."""


def picked(args: argparse.Namespace) -> bool:
    return True


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    from .steps.timing import throughput

    result = throughput(sequence, config, frames=args.frames or 60, start=args.start, runs=args.runs,
                        progress=not args.quiet)
    for line in summary_lines(result, config):
        print(line)
    return {"throughput": result}


def summary_lines(result: dict, config) -> list[str]:
    """What ``twohr bench`` prints of a throughput result: FPS, memory and ATE, the network it chose, ORB-SLAM3's
    figures, and the stages' latency."""
    lines = [f"{result['frames']} frames x {result['runs']} runs: {result['fps_median']} FPS "
             f"(ORB baseline {result['baseline_fps_median']} FPS, ratio {result['speed_ratio_to_baseline']}); "
             f"peak RSS {result['peak_rss_mib']} MiB"
             + (f" ({result['peak_rss_mib_with_orbslam3']} MiB once ORB-SLAM3 ran in this process)"
                if "peak_rss_mib_with_orbslam3" in result else "")
             + f"; ATE median {result['ate_rmse_median']} m"]
    if "detector_model" in result["chosen"]:
        lines.append(f"keyframe network {result['chosen']['detector_model']} at input scale "
                     f"{result['chosen'].get('detector_input_scale', config.detector.input_scale)}")
    lines += orbslam3_lines(result["orbslam3"])
    lines.append(f"{'stage':10} {'median ms':>10} {'p90 ms':>8}")
    lines += [f"{stage:10} {v['median']:10.1f} {v['p90']:8.1f}" for stage, v in result["stages_ms"].items()]
    return lines


def orbslam3_lines(orbslam3: dict | str) -> list[str]:
    if not isinstance(orbslam3, dict):
        return [f"ORB-SLAM3: {orbslam3}"]
    same = orbslam3["like_for_like"]
    lines = [f"ORB-SLAM3 RGB-D (pyorbslam3): {orbslam3['ms_per_frame_median']} ms/frame median; ours/ORB-SLAM3 "
             f"ms per frame: {orbslam3['ratio_ms_per_frame']} (ours decoding its frames as it runs)"]
    if "not_run" in same:
        lines.append(f"like for like: not run ({same['not_run']})")
    else:
        lines.append(f"like for like, frames decoded before the clock, means: ours {same['ours_ms_per_frame']} "
                     f"ms/frame, ORB-SLAM3 {same['orbslam3_ms_per_frame']} ms/frame; ratio "
                     f"{same['ratio_ms_per_frame']}; our ATE median in these runs {same['ours_ate_rmse_median']} m")
    return lines
