"""``twohr bench --live`` (``twohr bench live``): live camera sessions over ``twohr up`` (``twohr camera --replay``
at 30 Hz, ``--frames`` frames, default 300), ``--runs`` times for each count of busy processes in ``--busy``; with
``--robots N``, N robots at once on one stack; with ``--edge``, each session also tracked by the robot itself.
live.md; bench.json: ``live`` (``rows``, ``robots``)."""

from __future__ import annotations

import argparse

from .common import add_camera_runs, add_link, add_replicas, add_robots, live_session_rows, report_table

NAME = "live"
HELP = "live camera sessions over twohr up, beside busy processes: posed, dropped, FPS, latency, ATE, RSS"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    if legacy:
        p.add_argument("--live", action="store_true", help="live camera sessions over twohr up (twohr camera "
                       "--replay at 30 Hz, --frames frames, default 300; --set overrides go to the sessions), --runs "
                       "times for each count of busy processes in --busy: frames posed and dropped, FPS, frame->pose "
                       "latency, ATE of the served and online trajectories, every service's RSS")
    p.add_argument("--busy", default="0,1,2", help="with --live: counts of busy processes beside the stack "
                   "(python3 -c 'while True: pass'), comma-separated (default 0,1,2)")
    add_link(p)
    p.add_argument("--edge", action="store_true", help="with --live: every session also with the robot tracking "
                   "itself (twohr camera --edge), beside the stack tracking it; bench.json live.robots[i] gives each "
                   "way's upstream_bytes_per_s")
    add_camera_runs(p)
    add_robots(p)
    add_replicas(p)


def picked(args: argparse.Namespace) -> bool:
    return args.live


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    from .steps.camera_sessions import format_table, robot_summary

    rows = live_session_rows(args, sequence, args.frames or 300, [int(b) for b in args.busy.split(",")], args.runs)
    report_table(out, "live", format_table(rows), args.argv)
    return {"live": {"rows": rows, "robots": robot_summary(rows)}}
