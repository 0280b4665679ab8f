"""``twohr bench --bus`` (``twohr bench bus``): frame -> pose latency and FPS over Zenoh (``twohr up`` as local
processes, or a stack already running behind ``--gateway``) against in-process runs of the same frames and config.
bench.json: ``bus`` (``in_process``, ``zenoh_runs``, ``zenoh_system``, ``zenoh``)."""

from __future__ import annotations

import argparse

from .common import add_robots, overrides

NAME = "bus"
HELP = "frame->pose latency and FPS over Zenoh against in-process"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    if legacy:
        p.add_argument("--bus", action="store_true", help="frame->pose latency and FPS over Zenoh (twohr up as "
                       "local processes) against in-process, same frames and config (--set overrides go to both); "
                       "FPS counts from the first pose to the last, and first_pose_s is the wait for the first map "
                       "(a replay at --rate plays on once its first frame is answered)")
    p.add_argument("--gateway", default=None, metavar="URL",
                   help="with --bus: measure the system already running behind this gateway (e.g. the compose "
                   "stack, http://127.0.0.1:8080) instead of starting twohr up; its data root must hold --sequence")
    p.add_argument("--router", default="tcp/127.0.0.1:7447", help="with --gateway: that system's Zenoh router")
    p.add_argument("--zenoh-config", default=None, metavar="FILE", help="with --gateway: the Zenoh client config "
                   "(endpoint and credentials) of that system, e.g. the one twohr up writes")
    p.add_argument("--api-token", default=None, help="with --gateway: its HTTP API token")
    add_robots(p)
    p.add_argument("--rate", type=float, default=1.0,
                   help="with --bus: source speed, 1 = the camera's real rate (30 Hz for the dev sequence), "
                   "0 = as fast as the pipeline answers (at most two frames in flight)")


def picked(args: argparse.Namespace) -> bool:
    return args.bus


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    import json

    from twohr.errors import ConfigError

    args.robots = 1 if args.robots is None else args.robots
    if args.robots < 1 or (args.robots > 1 and args.gateway):
        raise ConfigError("--robots takes a count of 1 or more, and more than 1 only without --gateway")
    frames = args.frames or 60
    local = in_process_runs(sequence, config, frames, args.runs, progress=not args.quiet)
    bus_runs = [zenoh_run(args, sequence, frames) for _ in range(args.runs)]
    report = {"in_process": in_process_figures(local), "zenoh_runs": bus_runs,
              "zenoh_system": args.gateway or "twohr up (local processes)", "zenoh": zenoh_medians(bus_runs)}
    print(json.dumps(report, indent=2))
    return {"bus": report}


def in_process_runs(sequence, config, frames: int, runs: int, progress: bool) -> list:
    from twohr_app.pipeline import run_sequence

    return [run_sequence(sequence, config, stop=frames, progress=progress) for _ in range(runs)]


def zenoh_run(args: argparse.Namespace, sequence, frames: int) -> dict:
    """One run over Zenoh: on the stack behind ``--gateway``, else on a ``twohr up`` started for it."""
    from .steps.bus_sessions import bus_latency, latency_summary, session_latency

    if not args.gateway:
        return bus_latency(sequence.root, overrides(args), frames, args.rate, robots=args.robots)
    from twohr.bus import BusConfig

    bus = BusConfig(config_file=args.zenoh_config) if args.zenoh_config else BusConfig(connect=[args.router])
    return latency_summary(session_latency(bus, args.gateway, sequence.root.name, frames, args.rate,
                                           config_overrides=overrides(args), api_token=args.api_token))


def in_process_figures(local: list) -> dict:
    import numpy as np

    from twohr_services.tracker.stages import keyframe_job_latency

    latency = np.concatenate([[s.ms_total for s in r.stats] for r in local])
    return {"fps_median": round(float(np.median([len(r.stats) / r.wall_s for r in local])), 3),
            "keyframe_jobs": keyframe_job_latency([job for r in local for job in r.keyframe_log]),
            "latency_ms": {"p50": round(float(np.percentile(latency, 50)), 1),
                           "p99": round(float(np.percentile(latency, 99)), 1)}}


def zenoh_medians(bus_runs: list[dict]) -> dict:
    import numpy as np

    from .steps.bus_sessions import keyframe_job_medians

    return {"fps_median": float(np.median([r["fps"] for r in bus_runs])),
            "latency_p50_median": float(np.median([r["latency_ms"]["p50"] for r in bus_runs])),
            "latency_p99_median": float(np.median([r["latency_ms"]["p99"] for r in bus_runs])),
            "dropped_percent_median": float(np.median([r["dropped_percent"] for r in bus_runs])),
            "keyframe_job_ms": keyframe_job_medians(bus_runs),
            "first_pose_s_median": float(np.median([np.nan if r["first_pose_s"] is None else r["first_pose_s"]
                                                     for r in bus_runs]))}
