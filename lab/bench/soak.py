"""``twohr bench --soak MINUTES`` (``twohr bench soak --minutes M``): one live camera session on the sequence looped
at 30 Hz for MINUTES: every service's RSS every 10 s and the FPS per minute, and their growth after a warm-up.
live.md (the session and the summary); bench.json: ``live`` and ``soak``."""

from __future__ import annotations

import argparse

from .common import add_camera_runs, add_link, live_session_rows, report_table

NAME = "soak"
HELP = "one live camera session looped at 30 Hz for MINUTES: RSS and FPS as it goes"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    minutes = ("--soak",) if legacy else ("--minutes",)
    p.add_argument(*minutes, dest="soak", type=float, metavar="MINUTES", **(
        {"default": None} if legacy else {"required": True}),
        help="one live camera session on the sequence looped at 30 Hz for MINUTES: every service's RSS "
        "every 10 s and the FPS per minute")
    busy = ("--soak-busy",) if legacy else ("--busy",)
    p.add_argument(*busy, dest="soak_busy", type=int, default=0, help="with --soak: busy processes beside the stack")
    add_link(p)
    add_camera_runs(p)


def picked(args: argparse.Namespace) -> bool:
    return bool(args.soak)


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    import json

    from .steps.camera_sessions import format_table, robot_summary, soak_summary

    frames = int(args.soak * 60 * 30) // args.camera_runs
    rows = live_session_rows(args, sequence, frames, [args.soak_busy], 1)
    soak = soak_summary(rows[0], args.soak)
    report_table(out, "live", f"{format_table(rows)}\n\nsoak: {json.dumps(soak)}", args.argv)
    return {"live": {"rows": rows, "robots": robot_summary(rows)}, "soak": soak}
