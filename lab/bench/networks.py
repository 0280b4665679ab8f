"""``twohr bench --networks`` (``twohr bench networks``): each keyframe network's latency as the detector runs it
(:mod:`twohr_lab.student.bench`). networks.md; bench.json: ``networks``."""

from __future__ import annotations

import argparse

from .common import report_table

NAME = "networks"
HELP = "each keyframe network's latency at input scales 0.75 and 0.5, with the ratio to faster2d2 f32"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    if legacy:
        p.add_argument("--networks", action="store_true", help="each keyframe network's latency (r2d2, faster2d2, "
                       "faster2d2-int8, faster2d2-int8-coarse, student) at input scales 0.75 and 0.5, f32 and, "
                       "where native, bf16, 1 thread, interleaved runs, with the ratio to faster2d2 f32")


def picked(args: argparse.Namespace) -> bool:
    return args.networks


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    from ..student.bench import format_table, network_latency

    result = network_latency(runs=args.runs, progress=not args.quiet)
    report_table(out, "networks", format_table(result), args.argv)
    return {"networks": result}
