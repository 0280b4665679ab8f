"""``twohr run`` and ``twohr demo``: the main job, detector -> yolo -> matcher -> tracker in one process."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from twohr.config import PRESETS
from twohr.paths import DEV_SEQUENCE


def load_config_and_sequence(args: argparse.Namespace):
    """The pipeline config (``--config``, ``--set``, ``--camera``) and the RGB-D sequence (``--sequence``) of
    a command that took :func:`add_run_options`; returns ``(config, sequence)``."""
    from twohr.config import load_config
    from twohr.dataset import RGBDSequence

    config = load_config(args.config, args.set or [], preset=args.preset)
    if args.camera:
        config.camera = args.camera
    sequence = RGBDSequence(args.sequence, camera=config.camera)
    return config, sequence


def write_run(out: Path, sequence, config, result) -> dict:
    """Write trajectories, per-frame stats, the config and (with ground truth) the evaluation; return a summary."""
    import yaml

    from twohr.evaluation import evaluate, loops_against_ground_truth
    from twohr.machine import machine
    from twohr.trajectory import write_tum
    from twohr_services.tracker.stages import keyframe_job_latency
    from twohr_services.tracker.trajectory import TRACKED_STATUSES

    from ..pipeline import stats_rows
    from ..report import keyframe_indices, plot_run_timeline, plot_run_trajectory, write_report_html

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
        "final_bundle_adjustment_s": round(result.refine_s, 3),
        "machine": machine(), **result.chosen,
        "ms_per_frame_median": {k: round(float(_median([getattr(s, k) for s in result.stats])), 2)
                                for k in ("ms_detector", "ms_yolo", "ms_tracker", "ms_total")} if frames else {},
    }
    if result.keyframe_log:
        log = result.keyframe_log
        summary["keyframe_jobs"] = {
            **keyframe_job_latency(log), "keyframes": sum(job.keyframe for job in log), "shed": result.shed_jobs,
            **{f"{key}_median": round(float(_median([getattr(job, key) for job in log])), 2)
               for key in ("ms_detector", "ms_yolo", "ms_mapping", "lag_frames")},
            "by_kind": {kind: {**keyframe_job_latency(jobs), "keyframes": sum(job.keyframe for job in jobs),
                               **{f"{key}_median": round(float(_median([getattr(job, key) for job in jobs])), 2)
                                  for key in ("ms_detector", "ms_yolo", "ms_mapping", "lag_frames")}}
                        for kind in sorted({job.kind for job in log})
                        for jobs in [[job for job in log if job.kind == kind]]},
        }
    if result.map is not None:
        summary["map"] = result.map.working_set()
    if result.loops is not None:
        summary["loops"] = result.loops.as_dict()
        if sequence.has_ground_truth():
            summary["loops"].update(loops_against_ground_truth(
                summary["loops"]["loops"], sequence.ground_truth(sequence.default_gt_extrinsic())))
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
          f"skipped {len(summary['skipped_frames'])}  per-frame ms {summary['ms_per_frame_median']}  "
          f"then final BA {summary.get('final_bundle_adjustment_s', 0):.1f} s"
          + (f"  detector {summary['detector_model']}" if "detector_model" in summary else "")
          + (f" at input scale {summary['detector_input_scale']}" if "detector_input_scale" in summary else ""))
    if "ate" in summary:
        a, r = summary["ate"], summary["ate_raw_gt"]
        print(f"ATE RMSE {a['ate']['rmse']:.4f} m (SE(3), max dt {a['max_dt']} s, camera-frame GT "
              f"'{a['gt_extrinsic']}'); raw marker GT {r['ate']['rmse']:.4f} m; online poses "
              f"{summary['ate_online']['ate']['rmse']:.4f} m; RPE 1 frame {a['rpe_frame']['rmse']:.4f} m, 1 s "
              f"{a['rpe_1s']['rmse']:.4f} m; jitter {a['jitter']['rmse']:.4f} m; "
              f"Sim(3) scale {a['sim3_scale'] or float('nan'):.3f}; "
              f"GT coverage {a['gt_coverage']:.1f} %")
    print(f"outputs in {out}/: report.html, trajectory.png, timeline.png, trajectory.txt, trajectory_online.txt, "
          "stats.csv, summary.json, config.yaml")


def _check_map_options(args: argparse.Namespace) -> None:
    from twohr.errors import TwohrError
    from twohr.mapmodes import MapMode

    if args.map_mode and not args.map:
        raise TwohrError("--map-mode needs --map FILE (the map to localize in or extend)")
    if args.map and not MapMode(args.map_mode or "localize").saves and args.save_map:
        raise TwohrError("--map-mode localize leaves the map as it was: there is nothing to --save-map "
                         "(--map-mode extend saves the map with this run's keyframes as a new file)")
    if args.map and args.save_map and Path(args.map).resolve() == Path(args.save_map).resolve():
        raise TwohrError("--save-map must name a new file: a map is never overwritten in place")
    if args.save_map:
        from twohr_services.tracker.mapfiles import map_name

        map_name(args.save_map)  # a name a map can have, before the run rather than after it


def _load_map(args: argparse.Namespace, config, sequence) -> tuple:
    """The map given by ``--map`` and what to report of it: (Map or None, its header or None, summary dict)."""
    if not args.map:
        return None, None, {}
    from twohr_services.tracker.mapfiles import load_map

    world, header, seconds = load_map(args.map, config, sequence.camera)
    print(f"map {header.name}: {header.keyframes} keyframes, {header.landmarks} landmarks, loaded in "
          f"{seconds * 1000:.0f} ms ({args.map_mode or 'localize'})", flush=True)
    return world, header, {"file": str(args.map), "name": header.name, "mode": args.map_mode or "localize",
                           "keyframes": header.keyframes, "landmarks": header.landmarks,
                           "load_s": round(seconds, 3)}


def _run(args: argparse.Namespace) -> int:
    from ..pipeline import run_sequence

    _check_map_options(args)
    config, sequence = load_config_and_sequence(args)
    frames = sequence.frame_range(args.start, args.frames, args.step)
    out = Path(args.out or f"runs/{sequence.name}")
    world, loaded, map_summary = _load_map(args, config, sequence)
    view = None
    if getattr(args, "view", False):
        from twohr.foxglove_live import view_url

        from ..live_view import PipelineLiveView

        view = PipelineLiveView(sequence, args.view_host, args.view_port)
        print(f"live view: {view_url(args.view_host, view.view.port)}", flush=True)
    try:
        result = run_sequence(sequence, config, start=frames.start, stop=frames.stop, step=frames.step,
                              progress=not args.quiet, on_frame=view, world=world)
    finally:
        if view is not None:
            view.close()
    summary = write_run(out, sequence, config, result)
    if map_summary:
        summary["map"] = {**map_summary, **_found_in_map(result)}
    if args.save_map:
        from twohr_services.tracker.mapfiles import save_map

        built_by = f"twohr run {sequence.name} frames {frames.start}-{frames.stop - 1}"
        header, size, seconds = save_map(args.save_map, result.map, config, built_by, parent=loaded)
        summary["saved_map"] = {"file": str(args.save_map), "name": header.name, "keyframes": header.keyframes,
                                "landmarks": header.landmarks, "size_bytes": size,
                                "bytes_per_keyframe": round(size / max(1, header.keyframes)),
                                "save_s": round(seconds, 3)}
    if map_summary or args.save_map:
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print_summary(summary, out)
    return 0


def _found_in_map(result) -> dict:
    """How long a run took to find the camera in a given map: frames and milliseconds to the first posed frame."""
    posed = [i for i, s in enumerate(result.stats) if s.status != "relocalising"]
    if not posed:
        return {"relocalised_after_frames": None, "relocalised_after_ms": None, "posed_percent": 0.0}
    first = posed[0]
    return {"relocalised_after_frames": first,
            "relocalised_after_ms": round(sum(s.ms_total for s in result.stats[:first + 1]), 1),
            "posed_percent": round(100 * len(posed) / len(result.stats), 2)}


def _demo(args: argparse.Namespace) -> int:
    from twohr import models

    args.config, args.set, args.preset, args.camera = None, [], None, None
    args.start, args.step, args.frames = 0, 1, None
    args.map, args.map_mode, args.save_map = None, None, None  # a demo builds its own map and keeps it in runs/
    config, sequence = load_config_and_sequence(args)
    print(f"twohr demo: {sequence.name}, {len(sequence)} RGB-D frames; models "
          f"{config.detector.model} + {config.yolo.model} + {config.matcher.model}")
    detector = models.auto_candidates() if config.detector.model == "auto" else [config.detector.model]
    for name in [*map(models.keyframe_network, detector), config.yolo.model, config.matcher.model]:
        models.model_path(name)
    args.quiet = False
    return _run(args)


def add_run_options(p: argparse.ArgumentParser) -> None:
    """``twohr run``'s options: the sequence, output folder, config and overrides, and the frame range."""
    p.add_argument("--sequence", required=True, help="TUM-layout RGB-D folder (rgb.txt, depth.txt, images)")
    p.add_argument("--out", default=None, help="output folder (default runs/<sequence name>)")
    p.add_argument("--config", default=None, help="YAML pipeline config (see twohr.config.PipelineConfig)")
    p.add_argument("--preset", default=None, choices=list(PRESETS), metavar="NAME",
                   help="a named configuration, applied over --config and under --set: the paper's ablation rows ("
                   + "; ".join(f"{name}: {preset.label}" for name, preset in PRESETS.items()) + ")")
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
    add_run_options(p)
    _add_view_options(p)
    p.add_argument("--save-map", default=None, metavar="FILE", help="save the map at the end as FILE (a .map file; "
                   "its name without .map is the map's name and frame); with --map-mode extend, the extended map")
    p.add_argument("--map", default=None, metavar="FILE", help="track in this saved map: no pose until the camera "
                   "is found in it (relocalisation, no prior pose), then poses in the map's frame")
    p.add_argument("--map-mode", choices=("localize", "extend"), default=None,
                   help="with --map: localize (default; new keyframes help tracking but the file is left as it was) "
                   "or extend (save the grown map with --save-map as a new file)")
    p.set_defaults(func=_run)

    p = sub.add_parser("demo", help="the main job end to end on the dev sequence, with a printed result")
    p.add_argument("--sequence", default=DEV_SEQUENCE, help="TUM-layout RGB-D folder")
    p.add_argument("--out", default="runs/demo", help="output folder")
    p.set_defaults(func=_demo)
