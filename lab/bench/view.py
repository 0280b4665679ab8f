"""``twohr bench --view`` (``twohr bench view``): CPU time per frame of ``twohr run --view`` with one viewer
subscribed to every channel, against the same run without the live view, over ``--frames`` frames (default 60).
bench.json: ``view``."""

from __future__ import annotations

import argparse

NAME = "view"
HELP = "CPU time per frame with the Foxglove live view against the same run without it"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    if legacy:
        p.add_argument("--view", action="store_true", help="CPU time per frame with the Foxglove live view "
                       "(twohr run --view, one viewer subscribed to every channel) against the same run without it")


def picked(args: argparse.Namespace) -> bool:
    return args.view


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    from .steps.view_cost import view_cost

    result = view_cost(sequence, config, frames=args.frames or 60, start=args.start, runs=args.runs,
                       progress=not args.quiet)
    median = result["cpu_ms_per_frame_median"]
    print(f"{result['frames']} frames x {result['runs']} runs: CPU {median['without_view']} ms/frame without "
          f"the live view, {median['with_view']} ms/frame with it and a viewer subscribed: "
          f"+{result['view_cpu_ms_per_frame']} ms ({result['view_cpu_percent']} %); "
          f"FPS {result['fps_median']}")
    return {"view": result}
