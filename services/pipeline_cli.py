"""``twohr run`` and ``twohr demo``: the main job, detector -> yolo -> matcher -> tracker in one process."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path


def _load(args: argparse.Namespace):
    from twohr.config import load_config
    from twohr.dataset import RGBDSequence

    config = load_config(args.config, args.set or [])
    if args.camera:
        config.camera = args.camera
    sequence = RGBDSequence(args.sequence, camera=config.camera)
    return config, sequence


def write_run(out: Path, sequence, config, result) -> dict:
    """Write trajectories, per-frame stats, the config and (with ground truth) the evaluation; return a summary."""
    import yaml

    from twohr.evaluation import evaluate
    from twohr.trajectory import write_tum

    from .pipeline import stats_rows
    from .run_report import keyframe_indices, plot_run_timeline, plot_run_trajectory, write_report_html
    from .tracker.core import TRACKED_STATUSES

    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.txt", result.trajectory, header=f"twohr {sequence.name}: refined, camera-to-world")
    write_tum(out / "trajectory_online.txt", result.online, header=f"twohr {sequence.name}: online poses")
    rows = stats_rows(result.stats)
    if rows:
        with open(out / "stats.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    (out / "config.yaml").write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    frames = len(result.stats)
    summary = {
        "sequence": str(sequence.root), "frames": frames, "skipped_frames": result.skipped,
        "tracked_percent": round(result.tracked_percent, 2),
        "lost_frames": [s.index for s in result.stats if s.status not in TRACKED_STATUSES],
        "fps": round(frames / result.wall_s, 3) if result.wall_s > 0 else None,
        "ms_per_frame_median": {k: round(float(_median([getattr(s, k) for s in result.stats])), 2)
                                for k in ("ms_detector", "ms_yolo", "ms_tracker", "ms_total")} if frames else {},
    }
    if result.keyframe_log:
        log = result.keyframe_log
        summary["keyframe_jobs"] = {
            "count": len(log), "keyframes": sum(job.keyframe for job in log),
            **{f"{key}_median": round(float(_median([getattr(job, key) for job in log])), 2)
               for key in ("ms_detector", "ms_yolo", "ms_mapping", "lag_frames")},
        }
    title = f"twohr on {sequence.name}"
    evaluation = None
    if sequence.has_ground_truth() and len(result.trajectory) >= 3:
        extrinsic = sequence.default_gt_extrinsic()
        for name, gt_extrinsic in (("ate", extrinsic), ("ate_raw_gt", "none")):
            for label, traj in (("", result.trajectory), ("_online", result.online)):
                report, arrays = evaluate(sequence.ground_truth(gt_extrinsic), traj, gt_extrinsic=gt_extrinsic)
                summary[f"{name}{label}"] = report.model_dump()
                if name == "ate" and not label:
                    evaluation, title = arrays, f"{title}: ATE RMSE {report.ate.rmse:.3f} m"
    keyframes = keyframe_indices(result)
    if len(result.trajectory):
        plot_run_trajectory(out / "trajectory.png", result.trajectory, result.stats, title, evaluation, keyframes)
    if result.stats:
        plot_run_timeline(out / "timeline.png", result.stats, f"twohr on {sequence.name}: per frame", keyframes)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    write_report_html(out, sequence.name, summary)
    return summary


def _median(values):
    import numpy as np

    return np.median(values) if values else float("nan")


def print_summary(summary: dict, out: Path) -> None:
    print(f"frames {summary['frames']}  tracked {summary['tracked_percent']:.1f} %  fps {summary['fps']}  "
          f"skipped {len(summary['skipped_frames'])}  per-frame ms {summary['ms_per_frame_median']}")
    if "ate" in summary:
        a, r = summary["ate"], summary["ate_raw_gt"]
        print(f"ATE RMSE {a['ate']['rmse']:.4f} m (SE(3), max dt {a['max_dt']} s, camera-frame GT "
              f"'{a['gt_extrinsic']}'); raw marker GT {r['ate']['rmse']:.4f} m; online poses "
              f"{summary['ate_online']['ate']['rmse']:.4f} m; RPE 1 s {a['rpe_1s']['rmse']:.4f} m; "
              f"GT coverage {a['gt_coverage']:.1f} %")
    print(f"outputs in {out}/: report.html, trajectory.png, timeline.png, trajectory.txt, trajectory_online.txt, "
          "stats.csv, summary.json, config.yaml")


def _run(args: argparse.Namespace) -> int:
    from .pipeline import run_sequence

    config, sequence = _load(args)
    out = Path(args.out or f"runs/{sequence.name}")
    view = None
    if getattr(args, "view", False):
        from twohr.foxglove_live import view_url

        from .live_run import PipelineLiveView

        view = PipelineLiveView(sequence, args.view_host, args.view_port)
        print(f"live view: {view_url(args.view_host, view.view.port)}", flush=True)
    try:
        result = run_sequence(sequence, config, start=args.start, stop=None if args.frames is None else
                              args.start + args.frames * args.step, step=args.step, progress=not args.quiet,
                              on_frame=view)
    finally:
        if view is not None:
            view.close()
    summary = write_run(out, sequence, config, result)
    print_summary(summary, out)
    return 0


def _demo(args: argparse.Namespace) -> int:
    from twohr import models

    args.config, args.set, args.camera, args.start, args.step, args.frames = None, [], None, 0, 1, None
    config, sequence = _load(args)
    print(f"twohr demo: {sequence.name}, {len(sequence)} RGB-D frames; models "
          f"{config.detector.model} + {config.yolo.model} + {config.matcher.model}")
    for name in (config.detector.model, config.yolo.model, config.matcher.model):
        models.model_path(name)
    args.quiet = False
    return _run(args)


def _bench(args: argparse.Namespace) -> int:
    from . import bench

    config, sequence = _load(args)
    out = Path(args.out or "runs/bench")
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {}
    if args.bus:
        import numpy as np

        from twohr.config import merge_overrides

        from .pipeline import run_sequence

        overrides = merge_overrides({}, args.set or [])
        frames = args.frames or 60
        local = [run_sequence(sequence, config, stop=frames, progress=not args.quiet) for _ in range(args.runs)]
        lat = np.concatenate([[s.ms_total for s in r.stats] for r in local])
        if args.gateway:  # an already-running stack, e.g. the compose containers
            bus_runs = [bench.latency_summary(bench.session_latency(args.router, args.gateway, sequence.root.name,
                                                                    frames, args.rate, config_overrides=overrides))
                        for _ in range(args.runs)]
        else:
            bus_runs = [bench.bus_latency(sequence.root, overrides, frames, args.rate) for _ in range(args.runs)]
        report["bus"] = {
            "in_process": {"fps_median": round(float(np.median([len(r.stats) / r.wall_s for r in local])), 3),
                           "latency_ms": {"p50": round(float(np.percentile(lat, 50)), 1),
                                          "p99": round(float(np.percentile(lat, 99)), 1)}},
            "zenoh_runs": bus_runs, "zenoh_system": args.gateway or "twohr up (local processes)",
            "zenoh": {"fps_median": float(np.median([r["fps"] for r in bus_runs])),
                      "latency_p50_median": float(np.median([r["latency_ms"]["p50"] for r in bus_runs])),
                      "latency_p99_median": float(np.median([r["latency_ms"]["p99"] for r in bus_runs])),
                      "dropped_percent_median": float(np.median([r["dropped_percent"] for r in bus_runs]))},
        }
        print(json.dumps(report["bus"], indent=2))
    elif args.view:
        result = bench.view_cost(sequence, config, frames=args.frames or 60, start=args.start, runs=args.runs,
                                 progress=not args.quiet)
        report["view"] = result
        median = result["cpu_ms_per_frame_median"]
        print(f"{result['frames']} frames x {result['runs']} runs: CPU {median['without_view']} ms/frame without "
              f"the live view, {median['with_view']} ms/frame with it and a viewer subscribed: "
              f"+{result['view_cpu_ms_per_frame']} ms ({result['view_cpu_percent']} %); "
              f"FPS {result['fps_median']}")
    elif args.ablations:
        rows = bench.ablations(sequence, config, stop=args.frames, progress=not args.quiet)
        rows.append(bench.static_camera_row(sequence))
        report["ablations"] = {"sequence": sequence.name, "frames": args.frames or len(sequence),
                               "ate": "RMSE after SE(3) Umeyama alignment, max dt 0.02 s, camera-frame GT",
                               "rows": rows}
        table = bench.format_table(rows)
        (out / "ablations.md").write_text(table + "\n")
        print(table)
    else:
        result = bench.throughput(sequence, config, frames=args.frames or 60, start=args.start, runs=args.runs,
                                  progress=not args.quiet)
        report["throughput"] = result
        print(f"{result['frames']} frames x {result['runs']} runs: {result['fps_median']} FPS "
              f"(ORB baseline {result['baseline_fps_median']} FPS, ratio {result['speed_ratio_to_baseline']}); "
              f"peak RSS {result['peak_rss_mib']} MiB; ATE median {result['ate_rmse_median']} m")
        orbslam3 = result["orbslam3"]
        if isinstance(orbslam3, dict):
            print(f"ORB-SLAM3 RGB-D (pyorbslam3): {orbslam3['ms_per_frame_median']} ms/frame; ours/ORB-SLAM3 "
                  f"ms per frame: {orbslam3['ratio_ms_per_frame']}")
        else:
            print(f"ORB-SLAM3: {orbslam3}")
        print(f"{'stage':10} {'median ms':>10} {'p90 ms':>8}")
        for stage, v in result["stages_ms"].items():
            print(f"{stage:10} {v['median']:10.1f} {v['p90']:8.1f}")
    (out / "bench.json").write_text(json.dumps(report, indent=2))
    print(f"written: {out / 'bench.json'}")
    return 0


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sequence", required=True, help="TUM-layout RGB-D folder (rgb.txt, depth.txt, images)")
    p.add_argument("--out", default=None, help="output folder (default runs/<sequence name>)")
    p.add_argument("--config", default=None, help="YAML pipeline config (see twohr.config.PipelineConfig)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config value, e.g. --set detector.max_keypoints=1000 (repeatable)")
    p.add_argument("--camera", default=None, help="camera preset (tum_fr1, tum_fr2, tum_fr3, bonn)")
    p.add_argument("--start", type=int, default=0, help="first frame")
    p.add_argument("--frames", type=int, default=None, help="process at most this many frames")
    p.add_argument("--step", type=int, default=1, help="use every n-th frame")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_view_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--view", action="store_true", help="stream the run live to Foxglove (a Foxglove WebSocket "
                   "server: image, keypoints, mask, pose, path, map points, calibration, tf)")
    p.add_argument("--view-host", default="127.0.0.1", help="with --view: interface to listen on")
    p.add_argument("--view-port", type=int, default=8765, help="with --view: port (default 8765; 0 = any free)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the full pipeline on a sequence; writes trajectory, stats and evaluation",
                       description="The whole pipeline in one process. By default (pipeline.mode=keyframes) every "
                       "frame is tracked by optical flow against the map while 2HR detection, YOLO, matching and "
                       "bundle adjustment run on keyframes in worker threads; --set pipeline.mode=every_frame runs "
                       "detector (2HR) -> yolo mask -> matcher -> tracker on every frame, as in the paper. Writes "
                       "the TUM trajectory (camera-to-world), per-frame stats and, with ground truth, the ATE "
                       "report and plot.")
    _add_run_options(p)
    _add_view_options(p)
    p.set_defaults(func=_run)

    p = sub.add_parser("bench", help="throughput and per-stage latency (or --ablations: the accuracy table)",
                       description="Without --ablations: FPS, per-stage ms (median, p90) and peak RSS of the pipeline "
                       "over --frames frames, --runs times, each paired with an ORB baseline run for a ratio. With "
                       "--ablations: ATE RMSE, S.D., %% tracked and ms/frame of ORB, R2D2, 2HR, 2HR+YOLO and the "
                       "full pipeline on the same tracker.")
    _add_run_options(p)
    p.set_defaults(sequence="../shared/data/rgbd_bonn_crowd_dev")
    for action in p._actions:
        if action.dest == "sequence":
            action.required = False
    p.add_argument("--runs", type=int, default=3, help="repetitions for throughput (median reported)")
    p.add_argument("--ablations", action="store_true", help="the ablation table instead of throughput")
    p.add_argument("--view", action="store_true", help="CPU time per frame with the Foxglove live view (twohr run "
                   "--view, one viewer subscribed to every channel) against the same run without it")
    p.add_argument("--bus", action="store_true", help="frame->pose latency and FPS over Zenoh (twohr up as local "
                   "processes) against in-process, same frames and config (--set overrides go to both)")
    p.add_argument("--gateway", default=None, metavar="URL",
                   help="with --bus: measure the system already running behind this gateway (e.g. the compose "
                   "stack, http://127.0.0.1:8080) instead of starting twohr up; its data root must hold --sequence")
    p.add_argument("--router", default="tcp/127.0.0.1:7447", help="with --gateway: that system's Zenoh router")
    p.add_argument("--rate", type=float, default=1.0,
                   help="with --bus: source speed, 1 = the camera's real rate (30 Hz for the dev sequence), "
                   "0 = as fast as the pipeline answers (at most two frames in flight)")
    p.set_defaults(func=_bench)

    p = sub.add_parser("demo", help="the main job end to end on the dev sequence, with a printed result")
    p.add_argument("--sequence", default="../shared/data/rgbd_bonn_crowd_dev", help="TUM-layout RGB-D folder")
    p.add_argument("--out", default="runs/demo", help="output folder")
    p.set_defaults(func=_demo)
