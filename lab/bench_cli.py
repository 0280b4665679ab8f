"""``twohr bench``: throughput and per-stage latency of the pipeline, the ablation table, latency over Zenoh.

The command-line shell of :mod:`twohr_lab.bench`; it shares ``twohr run``'s options.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from twohr.paths import DEV_SEQUENCE
from twohr_app.commands.run import add_run_options, load_config_and_sequence

from .stamp import provenance, stamp_line


def _bench(args: argparse.Namespace) -> int:
    from . import bench

    config, sequence = load_config_and_sequence(args)
    out = Path(args.out or "runs/bench")
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {}
    if args.fleet is not None:
        from twohr import keys
        from twohr.config import merge_overrides
        from twohr.errors import ConfigError
        from twohr_app.commands.up import parse_replicas

        from . import fleet

        if args.fleet < 1:
            raise ConfigError(f"--fleet {args.fleet}: give a count of robots, 1 or more")
        from twohr_app.edge import parse_server_stages

        server = parse_server_stages(args.server_stages) if args.server_stages else tuple(keys.NETWORK_SERVICES)
        result = fleet.fleet_bench(sequence, config, args.fleet, frames=args.frames, start=args.start,
                                   replicas=parse_replicas(args.replicas),
                                   config_overrides=merge_overrides({}, args.set or []), progress=not args.quiet,
                                   server_stages=server)
        report["fleet"] = result
        # the stack twohr up starts by default, serving every network of a robot it tracks itself
        if not (args.set or args.replicas or args.config or args.preset or args.server_stages):
            from twohr_app.capacity import keep_bench

            if result["max_robots"] < args.fleet:  # a limit found; all N carried is only a lower bound
                kept = keep_bench(result["max_robots"])
                print(f"kept for twohr up --max-robots auto: {kept.line()}")
            else:
                print(f"not kept for twohr up --max-robots auto: all {args.fleet} robots were carried (try more)")
        table = fleet.format_table(result)
        (out / "fleet.md").write_text(f"{stamp_line(args.argv)}\n\n{table}\n")
        print(table)
    elif args.share:
        import numpy as np

        from . import comap

        rows = comap.share_runs(sequence, runs=args.runs, progress=not args.quiet)
        report["share"] = {"rows": rows, "joint_ate_median": float(np.median([r["joint_ate"] for r in rows])),
                           "joint_ate_at_most_0_025": sum(r["joint_ate"] <= 0.025 for r in rows)}
        table = comap.format_table(rows)
        (out / "share.md").write_text(f"{stamp_line(args.argv)}\n\n{table}\n")
        print(table)
    elif args.live or args.soak:
        from . import live

        if args.soak:
            frames, busy, repeats = int(args.soak * 60 * 30) // args.camera_runs, [args.soak_busy], 1
        else:
            frames, busy, repeats = args.frames or 300, [int(b) for b in args.busy.split(",")], args.runs
        from twohr.config import merge_overrides

        links = {"tcp": [False], "tls": [True], "both": [False, True]}[args.link]
        tracking = ("central", "edge") if args.edge else ("central",)
        if args.edge and (args.soak or args.camera_runs != 1):
            from twohr.errors import ConfigError

            raise ConfigError("--edge runs one camera per session: not with --soak or --camera-runs")
        overrides = merge_overrides({}, args.set or [])
        if args.robots is not None or args.replicas:  # robots on one stack, each with its own camera
            from twohr_app.commands.up import parse_replicas

            replicas = parse_replicas(args.replicas)
            rows = [row for tls in links for row in live.fleet_runs(
                sequence, args.robots or 1, frames, busy, repeats, progress=not args.quiet, config_overrides=overrides,
                tls=tls, replicas=replicas, tracking=tracking)]
        else:
            rows = [row for tls in links for row in live.live_runs(
                sequence, frames, busy, repeats, progress=not args.quiet, camera_runs=args.camera_runs,
                config_overrides=overrides, tls=tls, tracking=tracking)]
        # each session's served trajectory stays out of bench.json: its ATE is there
        rows = [{key: value for key, value in row.items() if key != "served_tum"} for row in rows]
        report["live"] = {"rows": rows, "robots": live.robot_summary(rows)}
        table = live.format_table(rows)
        if args.soak:
            report["soak"] = live.soak_summary(rows[0], args.soak)
            table += f"\n\nsoak: {json.dumps(report['soak'])}"
        (out / "live.md").write_text(f"{stamp_line(args.argv)}\n\n{table}\n")
        print(table)
    elif args.bus:
        import numpy as np

        from twohr.errors import ConfigError

        args.robots = 1 if args.robots is None else args.robots
        if args.robots < 1 or (args.robots > 1 and args.gateway):
            raise ConfigError("--robots takes a count of 1 or more, and more than 1 only without --gateway")

        from twohr.config import merge_overrides
        from twohr_app.pipeline import run_sequence
        from twohr_services.tracker.stages import keyframe_job_latency

        overrides = merge_overrides({}, args.set or [])
        frames = args.frames or 60
        local = [run_sequence(sequence, config, stop=frames, progress=not args.quiet) for _ in range(args.runs)]
        lat = np.concatenate([[s.ms_total for s in r.stats] for r in local])
        if args.gateway:  # an already-running stack, e.g. the compose containers
            from twohr.bus import BusConfig

            bus = BusConfig(config_file=args.zenoh_config) if args.zenoh_config else BusConfig(connect=[args.router])
            bus_runs = [bench.latency_summary(bench.session_latency(
                bus, args.gateway, sequence.root.name, frames, args.rate, config_overrides=overrides,
                api_token=args.api_token)) for _ in range(args.runs)]
        else:
            bus_runs = [bench.bus_latency(sequence.root, overrides, frames, args.rate, robots=args.robots)
                        for _ in range(args.runs)]
        report["bus"] = {
            "in_process": {"fps_median": round(float(np.median([len(r.stats) / r.wall_s for r in local])), 3),
                           "keyframe_jobs": keyframe_job_latency([job for r in local for job in r.keyframe_log]),
                           "latency_ms": {"p50": round(float(np.percentile(lat, 50)), 1),
                                          "p99": round(float(np.percentile(lat, 99)), 1)}},
            "zenoh_runs": bus_runs, "zenoh_system": args.gateway or "twohr up (local processes)",
            "zenoh": {"fps_median": float(np.median([r["fps"] for r in bus_runs])),
                      "latency_p50_median": float(np.median([r["latency_ms"]["p50"] for r in bus_runs])),
                      "latency_p99_median": float(np.median([r["latency_ms"]["p99"] for r in bus_runs])),
                      "dropped_percent_median": float(np.median([r["dropped_percent"] for r in bus_runs])),
                      "keyframe_job_ms": bench.keyframe_job_medians(bus_runs),
                      "first_pose_s_median": float(np.median([np.nan if r["first_pose_s"] is None else r["first_pose_s"]
                                                               for r in bus_runs]))},
        }
        print(json.dumps(report["bus"], indent=2))
    elif args.view_tls:
        result = bench.view_tls_fps(sequence, frames=args.frames or 2000, runs=args.runs)
        report["view_tls"] = result
        fps, camera = result["fps_median"], result["camera_rate"]
        print(f"live view, {result['frames']} frames x {result['runs']} runs ({result['image_kb_mean']} kB JPEG "
              f"each), one viewer: {fps['ws']} FPS on ws://, {fps['wss']} FPS on wss:// with a token "
              f"({result['tls_fps_change_percent']} %); at {camera['hz']:g} Hz CPU ms/frame: server "
              f"{camera['server_cpu_ms_per_frame']}, viewer {camera['viewer_cpu_ms_per_frame']}; "
              f"{result['machine']['cpu_model']}")
    elif args.view:
        result = bench.view_cost(sequence, config, frames=args.frames or 60, start=args.start, runs=args.runs,
                                 progress=not args.quiet)
        report["view"] = result
        median = result["cpu_ms_per_frame_median"]
        print(f"{result['frames']} frames x {result['runs']} runs: CPU {median['without_view']} ms/frame without "
              f"the live view, {median['with_view']} ms/frame with it and a viewer subscribed: "
              f"+{result['view_cpu_ms_per_frame']} ms ({result['view_cpu_percent']} %); "
              f"FPS {result['fps_median']}")
    elif args.networks:
        from .student.bench import format_table, network_latency

        result = network_latency(runs=args.runs, progress=not args.quiet)
        report["networks"] = result
        table = format_table(result)
        (out / "networks.md").write_text(f"{stamp_line(args.argv)}\n\n{table}\n")
        print(table)
    elif args.ablations:
        rows = bench.ablations(sequence, config, stop=args.frames, progress=not args.quiet)
        rows.append(bench.static_camera_row(sequence))
        report["ablations"] = {"sequence": sequence.name, "frames": args.frames or len(sequence),
                               "ate": "RMSE after SE(3) Umeyama alignment, max dt 0.02 s, camera-frame GT",
                               "rows": rows}
        table = bench.format_table(rows)
        (out / "ablations.md").write_text(f"{stamp_line(args.argv)}\n\n{table}\n")
        print(table)
    else:
        result = bench.throughput(sequence, config, frames=args.frames or 60, start=args.start, runs=args.runs,
                                  progress=not args.quiet)
        report["throughput"] = result
        print(f"{result['frames']} frames x {result['runs']} runs: {result['fps_median']} FPS "
              f"(ORB baseline {result['baseline_fps_median']} FPS, ratio {result['speed_ratio_to_baseline']}); "
              f"peak RSS {result['peak_rss_mib']} MiB"
              + (f" ({result['peak_rss_mib_with_orbslam3']} MiB once ORB-SLAM3 ran in this process)"
                 if "peak_rss_mib_with_orbslam3" in result else "")
              + f"; ATE median {result['ate_rmse_median']} m")
        if "detector_model" in result["chosen"]:
            print(f"keyframe network {result['chosen']['detector_model']} at input scale "
                  f"{result['chosen'].get('detector_input_scale', config.detector.input_scale)}")
        orbslam3 = result["orbslam3"]
        if isinstance(orbslam3, dict):
            same = orbslam3["like_for_like"]
            print(f"ORB-SLAM3 RGB-D (pyorbslam3): {orbslam3['ms_per_frame_median']} ms/frame median; ours/ORB-SLAM3 "
                  f"ms per frame: {orbslam3['ratio_ms_per_frame']} (ours decoding its frames as it runs)")
            if "not_run" in same:
                print(f"like for like: not run ({same['not_run']})")
            else:
                print(f"like for like, frames decoded before the clock, means: ours {same['ours_ms_per_frame']} "
                      f"ms/frame, ORB-SLAM3 {same['orbslam3_ms_per_frame']} ms/frame; ratio "
                      f"{same['ratio_ms_per_frame']}; our ATE median in these runs {same['ours_ate_rmse_median']} m")
        else:
            print(f"ORB-SLAM3: {orbslam3}")
        print(f"{'stage':10} {'median ms':>10} {'p90 ms':>8}")
        for stage, v in result["stages_ms"].items():
            print(f"{stage:10} {v['median']:10.1f} {v['p90']:8.1f}")
    (out / "bench.json").write_text(json.dumps({**report, "provenance": provenance(args.argv)}, indent=2))
    print(f"written: {out / 'bench.json'}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``twohr bench``."""
    p = sub.add_parser("bench", help="throughput and per-stage latency (or --ablations: the accuracy table)",
                       description="Without --ablations: FPS, per-stage ms (median, p90) and peak RSS of the pipeline "
                       "over --frames frames, --runs times, each paired with an ORB baseline run for a ratio. With "
                       "--ablations: ATE RMSE, S.D., %% tracked and ms/frame of ORB, R2D2, 2HR, 2HR+YOLO and the "
                       "full pipeline on the same tracker.")
    add_run_options(p)
    p.set_defaults(sequence=DEV_SEQUENCE)
    for action in p._actions:
        if action.dest == "sequence":
            action.required = False
    p.add_argument("--runs", type=int, default=3, help="repetitions for throughput (median reported)")
    p.add_argument("--ablations", action="store_true", help="the ablation table instead of throughput")
    p.add_argument("--networks", action="store_true", help="each keyframe network's latency (r2d2, faster2d2, "
                   "faster2d2-int8, faster2d2-int8-coarse, student) at input scales 0.75 and 0.5, f32 and, where "
                   "native, bf16, 1 thread, interleaved runs, with the ratio to faster2d2 f32")
    p.add_argument("--view", action="store_true", help="CPU time per frame with the Foxglove live view (twohr run "
                   "--view, one viewer subscribed to every channel) against the same run without it")
    p.add_argument("--view-tls", action="store_true", help="frames per second one viewer receives from the live "
                   "view on ws:// and on wss:// with a token (the fleet's TLS), the sequence's JPEG frames sent as "
                   "fast as the viewer takes them (--frames, default 2000; --runs pairs), and the CPU per frame at "
                   "30 Hz")
    p.add_argument("--bus", action="store_true", help="frame->pose latency and FPS over Zenoh (twohr up as local "
                   "processes) against in-process, same frames and config (--set overrides go to both); FPS counts "
                   "from the first pose to the last, and first_pose_s is the wait for the first map (a replay at "
                   "--rate plays on once its first frame is answered)")
    p.add_argument("--gateway", default=None, metavar="URL",
                   help="with --bus: measure the system already running behind this gateway (e.g. the compose "
                   "stack, http://127.0.0.1:8080) instead of starting twohr up; its data root must hold --sequence")
    p.add_argument("--router", default="tcp/127.0.0.1:7447", help="with --gateway: that system's Zenoh router")
    p.add_argument("--zenoh-config", default=None, metavar="FILE", help="with --gateway: the Zenoh client config "
                   "(endpoint and credentials) of that system, e.g. the one twohr up writes")
    p.add_argument("--api-token", default=None, help="with --gateway: its HTTP API token")
    p.add_argument("--share", action="store_true", help="two live robots that track themselves build one map at "
                   "once (map mode share): when and where the map server merges the second, its cost, the bytes "
                   "each way, the frames posed in the map's frame and the joint ATE, --runs times (share.md)")
    p.add_argument("--live", action="store_true", help="live camera sessions over twohr up (twohr camera --replay "
                   "at 30 Hz, --frames frames, default 300; --set overrides go to the sessions), --runs times for each "
                   "count of busy processes in --busy: "
                   "frames posed and dropped, FPS, frame->pose latency, ATE of the served and online trajectories, "
                   "every service's RSS")
    p.add_argument("--busy", default="0,1,2", help="with --live: counts of busy processes beside the stack "
                   "(python3 -c 'while True: pass'), comma-separated (default 0,1,2)")
    p.add_argument("--link", choices=["tcp", "tls", "both"], default="tcp", help="with --live or --soak: the "
                   "stack on plain TCP with passwords (default), on a fleet's keys made for the run (mutual TLS, "
                   "HTTPS, each robot with its own bundle), or both, one after the other")
    p.add_argument("--soak", type=float, default=None, metavar="MINUTES",
                   help="one live camera session on the sequence looped at 30 Hz for MINUTES: every service's RSS "
                   "every 10 s and the FPS per minute")
    p.add_argument("--soak-busy", type=int, default=0, help="with --soak: busy processes beside the stack")
    p.add_argument("--server-stages", default=None, metavar="LIST", help="with --fleet: the networks the server "
                   "runs for each robot, comma-separated (default: all three; detector: twohr camera --edge's default, "
                   "the robot running yolo and the matcher itself)")
    p.add_argument("--edge", action="store_true", help="with --live: every session also with the robot tracking "
                   "itself (twohr camera --edge), beside the stack tracking it; bench.json live.robots[i] gives each "
                   "way's upstream_bytes_per_s")
    p.add_argument("--camera-runs", type=int, default=1, help="with --live or --soak: feed each session that many "
                   "separate twohr camera runs of its frames (each a new client whose stamps start again, as a camera "
                   "driver restarted), e.g. --live --frames 560 --camera-runs 6 --busy 0")
    p.add_argument("--robots", type=int, default=None, help="with --bus: that many robots replay the sequence at once "
                   "through one stack (one detector service for all); per-robot figures and how many kept camera "
                   "rate. With --live: that many live robots at once, each its own twohr camera at 30 Hz on its own "
                   "stretch of the sequence: posed %%, ATE, latency per robot and the stack's CPU per robot")
    p.add_argument("--replicas", action="append", metavar="SERVICE=N", help="with --live or --fleet: replicas of "
                   "network services in the stack, as twohr up --replicas takes them")
    p.add_argument("--fleet", type=int, default=None, metavar="N", help="the server's capacity for robots that "
                   "track themselves: the keyframe jobs of one run over --frames frames, recorded, then replayed by N "
                   "robots at once against the stack's detector, yolo and matcher at their recorded times; each "
                   "robot's keyframe job latency (p50, p99), the server's CPU, and the largest n <= N whose every p99 "
                   "stays within 1 s (smaller n tried where N fails); bench.json: fleet.robots, "
                   "fleet.keyframe_p99_ms, fleet.max_robots")
    p.add_argument("--rate", type=float, default=1.0,
                   help="with --bus: source speed, 1 = the camera's real rate (30 Hz for the dev sequence), "
                   "0 = as fast as the pipeline answers (at most two frames in flight)")
    p.set_defaults(func=_bench)
