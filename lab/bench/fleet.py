"""``twohr bench --fleet N`` (``twohr bench fleet --robots N``): how many robots that track themselves one server's
network services carry (:mod:`~twohr_lab.bench.steps.keyframe_replay`); the server runs all three networks unless
``--server-stages`` says fewer. With the default stack, a limit found is kept for ``twohr up --max-robots auto``
(:mod:`twohr_app.capacity`). fleet.md; bench.json: ``fleet`` (``robots``, ``keyframe_p99_ms``, ``max_robots``)."""

from __future__ import annotations

import argparse

from .common import add_replicas, overrides, report_table

NAME = "fleet"
HELP = "the server's capacity for robots that track themselves: N robots' keyframe jobs replayed at once"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    count = ("--fleet",) if legacy else ("--robots",)
    p.add_argument("--server-stages", default=None, metavar="LIST", help="with --fleet: the networks the server "
                   "runs for each robot, comma-separated (default: all three; detector: twohr camera --edge's default, "
                   "the robot running yolo and the matcher itself)")
    add_replicas(p)
    p.add_argument(*count, dest="fleet", type=int, metavar="N", **({"default": None} if legacy else {"required": True}),
                   help="the server's capacity for robots that track themselves: the keyframe jobs of one run over "
                   "--frames frames, recorded, then replayed by N robots at once against the stack's detector, yolo "
                   "and matcher at their recorded times; each robot's keyframe job latency (p50, p99), the server's "
                   "CPU, and the largest n <= N whose every p99 stays within 1 s (smaller n tried where N fails); "
                   "bench.json: fleet.robots, fleet.keyframe_p99_ms, fleet.max_robots")


def picked(args: argparse.Namespace) -> bool:
    return args.fleet is not None


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    from twohr.errors import ConfigError
    from twohr_app.commands.up import parse_replicas

    from .steps.keyframe_replay import fleet_bench, format_table

    if args.fleet < 1:
        raise ConfigError(f"--fleet {args.fleet}: give a count of robots, 1 or more")
    stages = server_stages(args)
    result = fleet_bench(sequence, config, args.fleet, frames=args.frames, start=args.start,
                         replicas=parse_replicas(args.replicas), config_overrides=overrides(args),
                         progress=not args.quiet, server_stages=stages)
    keep_for_twohr_up(args, result)
    report_table(out, "fleet", format_table(result), args.argv)
    return {"fleet": result}


def server_stages(args: argparse.Namespace) -> tuple[str, ...]:
    """The networks the server runs for the robots: ``--server-stages``, else all three (the stack ``twohr up``
    starts by default, serving every network of a robot that tracks itself)."""
    from twohr import keys
    from twohr_app.edge import parse_server_stages

    return parse_server_stages(args.server_stages) if args.server_stages else tuple(keys.NETWORK_SERVICES)


def keep_for_twohr_up(args: argparse.Namespace, result: dict) -> None:
    """Keep the limit found for ``twohr up --max-robots auto`` where the bench ran the stack ``twohr up`` starts by
    default (every network served, the default config and replicas)."""
    if args.set or args.replicas or args.config or args.preset or args.server_stages:
        return
    from twohr_app.capacity import keep_bench

    if result["max_robots"] < args.fleet:  # a limit found; all N carried is only a lower bound
        print(f"kept for twohr up --max-robots auto: {keep_bench(result['max_robots']).line()}")
    else:
        print(f"not kept for twohr up --max-robots auto: all {args.fleet} robots were carried (try more)")
