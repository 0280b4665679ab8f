"""What the bench's studies share: their common options, the output folder and the report files, and the live
camera sessions that ``--live`` and ``--soak`` both run.

Options used by several studies (``--runs``, ``--robots``, ``--replicas``, ``--link``, ``--camera-runs``) are added
here, once per parser: the one ``twohr bench`` parser of every study holds each a single time.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from twohr.paths import DEV_SEQUENCE
from twohr_app.commands.run import add_run_options

from ..stamp import provenance, stamp_line

#: where the reports go without --out
DEFAULT_OUT = "runs/bench"


def _once(p, *flags: str, **options) -> None:
    """Add an option unless ``p`` (a parser or one of its groups) has it already."""
    if flags[0] not in p._option_string_actions:
        p.add_argument(*flags, **options)


def add_common_options(p: argparse.ArgumentParser) -> None:
    """``twohr run``'s options (the sequence defaulting to the dev sequence) and ``--runs``."""
    add_run_options(p)
    for action in p._actions:
        if action.dest == "sequence":
            action.required, action.default = False, DEV_SEQUENCE
    add_runs(p)


def add_runs(p) -> None:
    _once(p, "--runs", type=int, default=3, help="repetitions for throughput (median reported)")


def add_robots(p) -> None:
    _once(p, "--robots", type=int, default=None, help="with --bus: that many robots replay the sequence at once "
          "through one stack (one detector service for all); per-robot figures and how many kept camera "
          "rate. With --live: that many live robots at once, each its own twohr camera at 30 Hz on its own "
          "stretch of the sequence: posed %%, ATE, latency per robot and the stack's CPU per robot")


def add_replicas(p) -> None:
    _once(p, "--replicas", action="append", metavar="SERVICE=N", help="with --live or --fleet: replicas of "
          "network services in the stack, as twohr up --replicas takes them")


def add_link(p) -> None:
    _once(p, "--link", choices=["tcp", "tls", "both"], default="tcp", help="with --live or --soak: the "
          "stack on plain TCP with passwords (default), on a fleet's keys made for the run (mutual TLS, "
          "HTTPS, each robot with its own bundle), or both, one after the other")


def add_camera_runs(p) -> None:
    _once(p, "--camera-runs", type=int, default=1, help="with --live or --soak: feed each session that many "
          "separate twohr camera runs of its frames (each a new client whose stamps start again, as a camera "
          "driver restarted), e.g. --live --frames 560 --camera-runs 6 --busy 0")


def output_folder(args: argparse.Namespace) -> Path:
    """``--out`` (default :data:`DEFAULT_OUT`), made."""
    out = Path(args.out or DEFAULT_OUT)
    out.mkdir(parents=True, exist_ok=True)
    return out


def report_table(out: Path, name: str, table: str, argv: list[str] | None) -> None:
    """``<out>/<name>.md``: the stamp line, then ``table``; and the table printed."""
    (out / f"{name}.md").write_text(f"{stamp_line(argv)}\n\n{table}\n")
    print(table)


def write_bench_json(out: Path, report: dict, argv: list[str] | None) -> Path:
    """``<out>/bench.json``: the studies' ``report`` and its provenance."""
    path = out / "bench.json"
    path.write_text(json.dumps({**report, "provenance": provenance(argv)}, indent=2))
    print(f"written: {path}")
    return path


def overrides(args: argparse.Namespace) -> dict:
    """The ``--set`` overrides as a nested dict (what a session's ``config`` takes)."""
    from twohr.config import merge_overrides

    return merge_overrides({}, args.set or [])


def live_session_rows(args: argparse.Namespace, sequence, frames: int, busy: list[int], repeats: int) -> list[dict]:
    """Live camera sessions on ``twohr up`` for ``--live`` and ``--soak``: one stack per ``--link``, and on it either
    ``--robots`` robots at once (or one, with ``--replicas``) or one robot's sessions after another. Each row without
    the session's served trajectory (its ATE is in it)."""
    from twohr.errors import ConfigError

    from .steps import camera_sessions

    links = {"tcp": [False], "tls": [True], "both": [False, True]}[args.link]
    tracking = ("central", "edge") if args.edge else ("central",)
    if args.edge and (args.soak or args.camera_runs != 1):
        raise ConfigError("--edge runs one camera per session: not with --soak or --camera-runs")
    if args.robots is not None or args.replicas:  # robots on one stack, each with its own camera
        from twohr_app.commands.up import parse_replicas

        replicas = parse_replicas(args.replicas)
        rows = [row for tls in links for row in camera_sessions.fleet_runs(
            sequence, args.robots or 1, frames, busy, repeats, progress=not args.quiet,
            config_overrides=overrides(args), tls=tls, replicas=replicas, tracking=tracking)]
    else:
        rows = [row for tls in links for row in camera_sessions.live_runs(
            sequence, frames, busy, repeats, progress=not args.quiet, camera_runs=args.camera_runs,
            config_overrides=overrides(args), tls=tls, tracking=tracking)]
    return [{key: value for key, value in row.items() if key != "served_tum"} for row in rows]
