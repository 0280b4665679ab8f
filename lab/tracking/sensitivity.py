"""One-at-a-time sensitivity of the dev ATE to the pipeline's settings: a thin loop over ``run_sequence``.

Each swept value is one ``twohr run`` with that ``--set`` on top of the others; in ``every_frame`` mode
the networks run once and the runs share their outputs (:class:`~twohr_lab.bench.steps.front_cache.FrontCache`)::

    .venv/bin/python -m twohr_lab.tracking.sensitivity --frames 560 --set pipeline.synchronous=true \\
        --sweep tracker.huber_px=1,4 --sweep tracker.match_radius_px=15,40 --out runs/sensitivity

Writes ``sensitivity.md`` (with the command and commit) and ``sensitivity.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from twohr.config import PipelineConfig, load_config, parse_override
from twohr.errors import ConfigError, TwohrError
from twohr.paths import DEV_SEQUENCE

from ..stamp import write_study

DEFAULT_SEQUENCE = DEV_SEQUENCE  # the name accuracy.py and consistency.py import


def parse_sweep(item: str) -> tuple[str, list]:
    """``section.key=v1,v2`` -> ("section.key", [v1, v2]), each value parsed as ``--set`` parses it."""
    key, _, raw = item.partition("=")
    if not key or not raw:
        raise ConfigError(f"--sweep {item!r} is not of the form section.key=v1,v2 (e.g. tracker.huber_px=1,4)")
    return key.strip(), [parse_override(f"{key}={value}")[1] for value in raw.split(",")]


def run_point(sequence, config: PipelineConfig, start: int, stop: int | None, step: int, fronts=None) -> dict:
    """ATE (online and refined, camera-frame ground truth), untracked frames, keyframes and ms/frame of one run."""
    from twohr.evaluation import evaluate
    from twohr_app.pipeline import run_sequence
    from twohr_services.tracker.trajectory import TRACKED_STATUSES

    front_cache = None
    if fronts is not None and config.pipeline.mode == "every_frame":
        front_cache = fronts.outputs(sequence, config, len(sequence) if stop is None else stop, False, start, step)
    run = run_sequence(sequence, config, start=start, stop=stop, step=step, progress=False, front_cache=front_cache)
    extrinsic = sequence.default_gt_extrinsic()
    gt = sequence.ground_truth(extrinsic)
    return {
        "ate_online": evaluate(gt, run.online, gt_extrinsic=extrinsic)[0].ate.rmse,
        "ate_refined": evaluate(gt, run.trajectory, gt_extrinsic=extrinsic)[0].ate.rmse,
        "untracked_frames": sum(s.status not in TRACKED_STATUSES for s in run.stats),
        "keyframes": sum(bool(s.keyframe) for s in run.stats),
        "ms_per_frame": float(np.median([s.ms_total for s in run.stats])) if run.stats else float("nan"),
    }


def sweep(sequence, config_file: str | None, overrides: list[str], sweeps: list[tuple[str, list]], start: int = 0,
          stop: int | None = None, step: int = 1, progress: bool = True) -> list[dict]:
    """Rows of the sensitivity table: the defaults first, then each swept value with the others unchanged."""
    from ..bench.steps.front_cache import FrontCache

    fronts = FrontCache()
    base = load_config(config_file, overrides)
    default = run_point(sequence, base, start, stop, step, fronts)
    rows = [{"parameter": "(all defaults)", "value": "", **default}]
    if progress:
        print(format_row(rows[-1]), flush=True)
    for key, values in sweeps:
        section, _, field = key.partition(".")
        current = getattr(getattr(base, section, None), field, None)
        rows.append({"parameter": key, "value": f"{current} (default)", **default})
        for value in values:
            point = run_point(sequence, load_config(config_file, [*overrides, f"{key}={json.dumps(value)}"]), start,
                              stop, step, fronts)
            rows.append({"parameter": key, "value": str(value), **point})
            if progress:
                print(format_row(rows[-1]), flush=True)
    return rows


def format_row(row: dict) -> str:
    return (f"| {row['parameter']} | {row['value']} | {row['ate_online']:.4f} | {row['ate_refined']:.4f} | "
            f"{row['untracked_frames']} | {row['keyframes']} | {row['ms_per_frame']:.0f} |")


def format_table(rows: list[dict]) -> str:
    """The Markdown table, with per-parameter and overall medians of the swept values plus the defaults."""
    lines = ["| parameter | value | ATE online (m) | ATE refined (m) | untracked frames | keyframes | ms/frame |",
             "|---|---|---|---|---|---|---|", format_row(rows[0])]
    online_all, refined_all = [rows[0]["ate_online"]], [rows[0]["ate_refined"]]
    for key in dict.fromkeys(r["parameter"] for r in rows[1:]):
        mine = [r for r in rows if r["parameter"] == key]
        lines += [format_row(r) for r in mine]
        lines.append(f"| {key} | median | {np.median([r['ate_online'] for r in mine]):.4f} | "
                     f"{np.median([r['ate_refined'] for r in mine]):.4f} | | | |")
        online_all += [r["ate_online"] for r in mine[1:]]
        refined_all += [r["ate_refined"] for r in mine[1:]]
    lines.append(f"| all settings | median (min-max) | {np.median(online_all):.4f} ({min(online_all):.4f}-"
                 f"{max(online_all):.4f}) | {np.median(refined_all):.4f} ({min(refined_all):.4f}-"
                 f"{max(refined_all):.4f}) | | | |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.tracking.sensitivity",
                                     description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", default=DEV_SEQUENCE, help="TUM-layout RGB-D folder with ground truth")
    parser.add_argument("--config", default=None, help="YAML pipeline config")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value for every run, e.g. --set pipeline.mode=every_frame")
    parser.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2",
                        help="rerun with each value of KEY, the others unchanged (repeatable), e.g. "
                        "--sweep tracker.huber_px=1,4")
    parser.add_argument("--start", type=int, default=0, help="first frame")
    parser.add_argument("--frames", type=int, default=None, help="process at most this many frames")
    parser.add_argument("--step", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--out", default="runs/sensitivity", help="output folder (default runs/sensitivity)")
    parser.add_argument("--quiet", action="store_true", help="do not print rows as they come")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)
    program = "python -m twohr_lab.tracking.sensitivity"
    try:
        from twohr.dataset import RGBDSequence

        if args.start < 0 or args.step < 1 or (args.frames is not None and args.frames < 1):
            raise ConfigError("--start must be >= 0, --step and --frames >= 1")
        sweeps = [parse_sweep(item) for item in args.sweep]
        sequence = RGBDSequence(args.sequence)
        if not sequence.has_ground_truth():
            raise ConfigError(f"{sequence.root} has no groundtruth.txt: the sensitivity table needs the ATE")
        stop = None if args.frames is None else args.start + args.frames * args.step
        rows = sweep(sequence, args.config, args.set, sweeps, args.start, stop, args.step, not args.quiet)
    except TwohrError as exc:
        print(f"sensitivity: error: {exc}", file=sys.stderr)
        return 2
    table = format_table(rows)
    out = write_study(args.out, "sensitivity", table, rows, argv, program)
    print(table)
    print(f"written: {out / 'sensitivity.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
